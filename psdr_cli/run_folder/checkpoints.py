"""Every file of a run's checkpoint (the unknowns' meshes, pictures and cameras, as records that
say what to write: :class:`Mesh`, :class:`Picture`, :class:`CameraPoses`), the final mesh and the
preview strips; the checkpoints of a finished run."""
from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import PsdrError
from ..scene.meshes import write_ply
from ..support import fileio
from .layout import RunFiles
from .refined_cameras import write_cameras


#: Names of the checkpoints in ``checkpoints/`` (other files there are not checkpoints).
CHECKPOINT_NAME = re.compile(r"iter_(\d+)\.ply")


def write_mesh(path: Path, V, F, uv=None):
    """PLY written atomically (opens in MeshLab and Blender), with the texture coordinates ``uv``
    of a textured run; refuses NaN or infinite vertices."""
    fileio.check_finite(path, V, "mesh")
    with fileio.atomic_path(path) as tmp:
        write_ply(tmp, V, F, uv)


def run_checkpoints(folder: Path):
    """[(iteration, path)] of a run folder (initial shape, checkpoints, final)."""
    folder = Path(folder)
    found = sorted((int(p.stem[5:]), p) for p in RunFiles(folder).checkpoints.glob("iter_*.ply")
                   if CHECKPOINT_NAME.fullmatch(p.name))  # not iter_abc.ply, a copy's "iter_0010 (2).ply"
    if not found:
        raise PsdrError(f"{folder}: no checkpoints (expected checkpoints/iter_NNNN.ply from `psdr optimize`)")
    return found


@dataclass(frozen=True)
class Mesh:
    """A mesh of a checkpoint: written to ``path`` as PLY (:func:`write_mesh`), with the texture
    coordinates ``uv`` of a textured run."""
    path: Path
    V: np.ndarray
    F: np.ndarray
    uv: np.ndarray | None = None

    def write(self, files: RunFiles, iteration: int):
        write_mesh(self.path, self.V, self.F, self.uv)


@dataclass(frozen=True)
class Picture:
    """A recovered image of a checkpoint, (H, W, 3) linear RGB: the EXR ``path`` (its header names
    the iteration), with ``png`` its tone-mapped preview beside it (``.png``), with ``preview``
    also ``previews/iter_NNNN_<preview>.png``."""
    path: Path
    image: np.ndarray
    png: bool = True
    preview: str | None = None

    def write(self, files: RunFiles, iteration: int):
        fileio.write_rgb_exr(self.path, self.image, {"psdr.iteration": str(iteration)})
        if self.png:
            fileio.write_preview(self.path.with_suffix(".png"), self.image)
        if self.preview:
            fileio.write_preview(files.previews / f"iter_{iteration:04d}_{self.preview}.png", self.image)


@dataclass(frozen=True)
class CameraPoses:
    """The refined cameras of a checkpoint: ``cameras.json`` and ``refined_cameras/``
    (:func:`psdr_cli.run_folder.refined_cameras.write_cameras`: the frames, their refined poses,
    the corrections {rotation, translation, stopped}, the coordinates' kind and the input's format)."""
    frames: list
    poses: list
    corrections: dict
    kind: str
    input_format: str | None = None

    def write(self, files: RunFiles, iteration: int):
        write_cameras(files.root, self.frames, self.poses, self.corrections, iteration, self.kind, self.input_format)


def write_checkpoint(files: RunFiles, iteration: int, parts: list, previews: dict | None = None,
                     zoom: int = 1) -> Path:
    """Every file of checkpoint ``iteration``: the unknowns' ``parts`` (:class:`Mesh`,
    :class:`Picture`, :class:`CameraPoses`, each written atomically) and per preview view
    {v: (target, current)} a target | current | |difference| strip with pixels enlarged ``zoom``
    times (a downsampled stage's images at the film's size). Returns checkpoints/iter_NNNN.ply."""
    for part in parts:
        part.write(files, iteration)
    for v, images in (previews or {}).items():
        full = [np.repeat(np.repeat(image, zoom, axis=0), zoom, axis=1) for image in images]
        fileio.write_preview(files.previews / f"iter_{iteration:04d}_view_{v:03d}.png", strip(*full))
    return files.checkpoint(iteration)


def strip(target, current, zoom: int = 3):
    """target | current | |difference| side by side, pixels enlarged ``zoom`` times, linear RGB."""
    gap = np.ones((target.shape[0], 2, 3))
    row = np.concatenate([target, gap, current, gap, np.abs(target - current)], axis=1)
    return np.repeat(np.repeat(row, zoom, axis=0), zoom, axis=1)
