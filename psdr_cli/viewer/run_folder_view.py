"""``psdr view RUN_FOLDER | MESH``: a finished or running run folder (or one mesh file) shown
read-only: the checkpoints on a slider, the cameras (cameras.json, else the cached targets'
headers), the loss from log.csv, the preview strips, the recovered environment map and texture
and the Chamfer plot of ``psdr evaluate``. Reads the folder (never its lock: a run may be
writing it meanwhile) and writes nothing."""
from __future__ import annotations

import re
import time
import warnings
from pathlib import Path

import numpy as np

from ..errors import PsdrError
from ..run_folder.checkpoints import CHECKPOINT_NAME
from ..run_folder.layout import RunFiles
from ..run_folder.log import read_log
from ..scene.meshes import read_mesh_file
from .frustums import cameras_json, target_cameras
from .pictures import read_exr, read_png
from .server import ViewerServer

PREVIEW_NAME = re.compile(r"iter_(\d+)_view_(\d+)\.png")


def is_run_folder(path: Path) -> bool:
    """Whether ``path`` is a folder ``psdr optimize`` wrote (checkpoints/, log.csv or run.json)."""
    files = RunFiles(path)
    return path.is_dir() and (files.checkpoints.is_dir() or files.log.is_file() or files.run.is_file())


def checkpoints(files: RunFiles) -> list:
    """[(iteration, path)] of the run's checkpoints so far (none yet for a run just started)."""
    if not files.checkpoints.is_dir():
        return []
    return sorted((int(p.stem[5:]), p) for p in files.checkpoints.glob("iter_*.ply") if CHECKPOINT_NAME.fullmatch(p.name))


def losses(files: RunFiles) -> tuple:
    """(iterations, losses) of log.csv, its complete rows only (a torn tail is left out silently)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rows = read_log(files.log)
    return [int(r["iteration"]) for r in rows], [float(r["loss"]) for r in rows]


def newest_preview(files: RunFiles, view: int) -> Path | None:
    """The newest ``previews/iter_NNNN_view_VVV.png`` strip of ``view`` (None: none written)."""
    return preview_at(files, view, None)


def preview_at(files: RunFiles, view: int, iteration: int | None) -> Path | None:
    """The preview strip of ``view`` at the newest checkpoint ≤ ``iteration`` (None: the newest)."""
    found = []
    for p in files.previews.glob(f"iter_*_view_{view:03d}.png") if files.previews.is_dir() else ():
        m = PREVIEW_NAME.fullmatch(p.name)
        if m and (iteration is None or int(m.group(1)) <= iteration):
            found.append((int(m.group(1)), p))
    return max(found)[1] if found else None


def run_cameras(files: RunFiles) -> list:
    """The run's cameras: cameras.json (refined poses, held-out views) when the run wrote one,
    else those of its cached targets."""
    path = files.root / "cameras.json"
    if path.is_file():
        try:
            return cameras_json(path)
        except (OSError, ValueError, KeyError, TypeError):
            pass  # being replaced, or foreign: fall back to the targets
    return target_cameras(files.targets)


def run_pictures(files: RunFiles) -> dict:
    """{panel name: 8-bit image} of what the run recovered and was scored on: the environment
    map, the albedo texture, the Chamfer plot of ``psdr evaluate`` (those that exist)."""
    out = {"environment map": read_exr(files.envmap) if files.envmap.is_file() else None,
           "texture": read_png(files.albedo.with_suffix(".png")) if files.albedo.with_suffix(".png").is_file() else None,
           "Chamfer (psdr evaluate)": read_png(files.root / "chamfer.png") if (files.root / "chamfer.png").is_file() else None}
    return {k: v for k, v in out.items() if v is not None}


def read_source(path: Path):
    """('run', RunFiles) or ('mesh', (V, F)) of what ``psdr view`` was given; a one-line error otherwise."""
    path = Path(path)
    if not path.exists():
        raise PsdrError(f"{path}: no such file or folder (expected a `psdr optimize` run folder or a .ply/.obj mesh)")
    if path.is_dir():
        if not is_run_folder(path):
            raise PsdrError(f"{path}: not a `psdr optimize` run folder (no checkpoints/, log.csv or run.json)")
        return "run", RunFiles(path)
    if path.suffix.lower() not in (".ply", ".obj"):
        raise PsdrError(f"{path}: expected a run folder or a .ply/.obj mesh")
    try:
        V, F = read_mesh_file(path)
    except Exception as exc:  # noqa: BLE001  (trimesh's many ways of failing on a bad file)
        raise PsdrError(f"{path}: cannot read the mesh ({exc})") from None
    if len(F) == 0:
        raise PsdrError(f"{path}: the mesh has no triangles")
    return "mesh", (V, F)


class FolderView:
    """A run folder on a :class:`ViewerServer`: a checkpoint slider, and the panels refreshed from
    the folder by :meth:`refresh` (a running run's new checkpoints join the slider)."""

    def __init__(self, server: ViewerServer, files: RunFiles):
        self.server, self.files = server, files
        self.found: list = []
        self.meshes: dict = {}
        self.slider = None
        self.follow = True  # the slider follows the newest checkpoint until the user moves it
        server.on_view(lambda _: self.show_strip())

    def refresh(self):
        """Re-read the folder: checkpoints, cameras, loss, strip, pictures, status."""
        found = checkpoints(self.files)
        if found != self.found:
            self.found = found
            self.update_slider()
        self.server.show_cameras(run_cameras(self.files))
        self.server.show_losses(*losses(self.files))
        for name, image in run_pictures(self.files).items():
            self.server.show_picture(name, image)
        self.show_checkpoint()

    def update_slider(self):
        if not self.found:
            return
        last = len(self.found) - 1
        if self.slider is None:
            self.slider = self.server.server.gui.add_slider("Checkpoint", 0, max(last, 1), 1, last, order=10)
            self.slider.on_update(lambda _: self.moved())
        self.slider.max = max(last, 1)
        if self.follow:
            self.slider.value = last

    def moved(self):
        self.follow = self.slider.value >= len(self.found) - 1
        self.show_checkpoint()

    def current(self) -> tuple | None:
        if not self.found:
            return None
        return self.found[min(int(self.slider.value), len(self.found) - 1)]

    def show_checkpoint(self):
        """The slider's checkpoint mesh, its strip and the status line."""
        chosen = self.current()
        if chosen is None:
            self.server.show_status(f"**{self.files.root.name}** · no checkpoint yet")
            return
        iteration, path = chosen
        if path not in self.meshes:
            try:
                self.meshes[path] = read_mesh_file(path)
            except Exception:  # noqa: BLE001  (being replaced: shown at the next refresh)
                return
        self.server.show_mesh(*self.meshes[path])
        self.server.show_status(f"**{self.files.root.name}** · checkpoint iteration {iteration} "
                                f"({len(self.found)} checkpoints)")
        self.show_strip()

    def show_strip(self):
        chosen = self.current()
        view = self.server.selected
        path = preview_at(self.files, view, chosen[0] if chosen else None)
        strip = read_png(path) if path else None
        cams = self.server.cameras
        if strip is None:
            self.server.show_strip(cams[view].image if view < len(cams) else None, f"view {view}: no preview")
        else:
            self.server.show_strip(strip, f"view {view}, {path.name[:9]}: target | render | error")


def open_view(path: Path, host: str = "127.0.0.1", port: int = 8080, warn=print):
    """(server, refresh) of ``psdr view PATH``: the page built, and a function that re-reads a run
    folder (nothing to re-read for a mesh file)."""
    kind, source = read_source(path)
    server = ViewerServer(host, port, f"psdr view {Path(path).name}", warn)
    if kind == "mesh":
        server.show_mesh(*source)
        server.show_status(f"**{Path(path).name}** · {len(source[0])} vertices, {len(source[1])} triangles")
        return server, lambda: None
    view = FolderView(server, source)
    view.refresh()
    return server, view.refresh


def serve(path: Path, host: str = "127.0.0.1", port: int = 8080, seconds: float | None = None,
          refresh_every: float = 2.0, warn=print, ready=print):
    """Serve ``psdr view PATH`` until Ctrl-C (or for ``seconds``), re-reading a run folder every
    ``refresh_every`` seconds; ``ready(url)`` once the page is up."""
    server, refresh = open_view(path, host, port, warn)
    ready(server.url)
    end = np.inf if seconds is None else time.monotonic() + seconds
    try:
        while time.monotonic() < end:
            time.sleep(min(refresh_every, max(end - time.monotonic(), 0.0)))
            refresh()
    finally:
        server.close()
