"""psdr: path-space differentiable rendering with guided boundary sampling (Yan et al. 2022).

Importing the package prepares Dr.Jit (libLLVM, kernel cache) before ``drjit`` is loaded; the
rest of the API is imported lazily so ``import psdr_cli`` stays cheap::

    import psdr_cli
    exp = psdr_cli.load_experiment("configs/demo.yaml")
    result = psdr_cli.render(exp, spp=16)
"""
from .backend import configure_environment as _configure_environment

_configure_environment()

from .config import Experiment, load_experiment  # noqa: E402
from .errors import ConfigError, PsdrError  # noqa: E402

__version__ = "0.1.0"

# (``optimize`` and ``evaluate`` are also module names: use ``psdr_cli.api.optimize`` / ``.evaluate``)
_LAZY = {"render": "api", "setup": "api", "build_scene": "scene", "grad": "api", "gradient_images": "api",
         "guide_stats": "api"}


def __getattr__(name):
    if name in _LAZY:
        import importlib
        return getattr(importlib.import_module(f".{_LAZY[name]}", __name__), name)
    raise AttributeError(name)


__all__ = ["Experiment", "load_experiment", "ConfigError", "PsdrError", "render", "setup", "build_scene", "grad",
           "gradient_images", "guide_stats"]
