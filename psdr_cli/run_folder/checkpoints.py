"""The meshes a run writes (checkpoints, final) and its preview strips; the checkpoints of a
finished run."""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from ..errors import PsdrError
from ..scene.meshes import write_ply
from ..support import fileio
from .layout import RunFiles


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


def write_checkpoint(files: RunFiles, iteration: int, V, F, *, texture=None, previews: dict | None = None,
                     zoom: int = 1, uv=None) -> Path:
    """checkpoints/iter_NNNN.ply (with the texture coordinates ``uv`` of a textured run); with
    ``texture`` (the recovered albedo texture, linear RGB)
    albedo.exr, albedo.png and its preview; per preview view {v: (target, current)} a target |
    current | |difference| strip with pixels enlarged ``zoom`` times (a downsampled stage's
    images at the film's size)."""
    path = files.checkpoint(iteration)
    write_mesh(path, V, F, uv)
    if texture is not None:
        fileio.write_rgb_exr(files.albedo, texture, {"psdr.iteration": str(iteration)})
        fileio.write_preview(files.albedo.with_suffix(".png"), texture)
        fileio.write_preview(files.previews / f"iter_{iteration:04d}_albedo.png", texture)
    for v, images in (previews or {}).items():
        full = [np.repeat(np.repeat(image, zoom, axis=0), zoom, axis=1) for image in images]
        fileio.write_preview(files.previews / f"iter_{iteration:04d}_view_{v:03d}.png", strip(*full))
    return path


def strip(target, current, zoom: int = 3):
    """target | current | |difference| side by side, pixels enlarged ``zoom`` times, linear RGB."""
    gap = np.ones((target.shape[0], 2, 3))
    row = np.concatenate([target, gap, current, gap, np.abs(target - current)], axis=1)
    return np.repeat(np.repeat(row, zoom, axis=0), zoom, axis=1)
