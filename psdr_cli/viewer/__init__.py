"""The web viewer (``psdr optimize --view``, ``psdr view``), on viser (the optional extra
``psdr[view]``). Its modules import viser at their top, so this package loads them only when a
viewer is asked for: :func:`live_viewer` (the loop's observer, :mod:`.live`) and :func:`serve`
(a run folder or mesh, :mod:`.run_folder_view`); the page itself is :mod:`.server`. Importing
this package imports nothing of viser."""
from __future__ import annotations

from importlib import import_module

from ..errors import PsdrError


def viewer_module(name: str):
    """The viewer module ``name``, imported now; a one-line error when viser is not installed."""
    try:
        return import_module(f"{__name__}.{name}")
    except ModuleNotFoundError as exc:
        if exc.name and exc.name.split(".")[0] == "viser":
            raise PsdrError("the viewer needs viser: pip install 'psdr[view]'") from None
        raise


def live_viewer(host: str = "127.0.0.1", port: int = 8080, warn=print, interval: float = 1.0):
    """A :class:`psdr_cli.viewer.live.LiveViewer` serving on ``host:port`` (the observer of
    :func:`psdr_cli.commands.optimize.optimize`)."""
    return viewer_module("live").LiveViewer(host, port, warn, interval)


def serve(path, host: str = "127.0.0.1", port: int = 8080, seconds: float | None = None, warn=print, ready=print):
    """``psdr view PATH``: serve a run folder or mesh until Ctrl-C or for ``seconds``."""
    return viewer_module("run_folder_view").serve(path, host, port, seconds, warn=warn, ready=ready)
