"""psdr: path-space differentiable rendering with guided boundary sampling (Yan et al. 2022).

Importing the package first prepares Dr.Jit (libLLVM, kernel cache, LLVM target: it writes
``DRJIT_*`` environment variables, :mod:`psdr_cli.support.backend`), before any module loads ``drjit``;
then the API of :mod:`psdr_cli.api` is available at the top level::

    import psdr_cli
    exp = psdr_cli.load_experiment("configs/demo.yaml")
    result = psdr_cli.render(exp, spp=16)

(``psdr_cli.render`` is the API function; the module is imported by its full
name, ``from psdr_cli.rendering.render import render_view``.)
"""
from .support.backend import configure_environment

configure_environment()  # must run before drjit is first imported (by the imports below)

from . import api  # noqa: E402
from .api import grad, gradient_images, guide_stats, load_experiment, render, setup  # noqa: E402
from .config.experiment_file import Experiment  # noqa: E402
from .errors import ConfigError, PsdrError  # noqa: E402
from .scene.build import build_scene  # noqa: E402

__version__ = "0.1.0"

__all__ = ["Experiment", "load_experiment", "ConfigError", "PsdrError", "api", "render", "setup", "build_scene",
           "grad", "gradient_images", "guide_stats"]
