"""Forward rendering of camera views with the interior estimator (``psdr render``). Reads the
experiment; writes one EXR (and a PNG preview) per view.

Pixels use a box filter: sample j of pixel (x, y) is the film point ((x, y) + ξ_j) / (W, H) with ξ_j
uniform in [0,1)², and the pixel value is the mean of its ``spp`` radiance samples. Large sample
counts run in passes of at most ``max_lanes`` paths so memory stays bounded; each pass is reduced
per pixel with ``dr.block_sum`` (deterministic, unlike atomic scatter-adds).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

from ..config.cameras_section import CameraConfig
from ..config.experiment_file import Experiment
from ..config.options import option_spp, parse_views
from ..estimators.interior import render_pass, split_views, views_pass
from ..estimators.passes import pass_seed, passes_for, views_seed
from ..estimators.registry import RENDER_STREAM
from ..scene.build import build_scene
from ..support import fileio


def camera_header(cam: CameraConfig) -> dict:
    """The EXR header ``psdr.camera`` of a camera: origin, target, up, fov, and its principal
    point offset only when it is not centred (a centred camera's header has no such key)."""
    d = {"origin": cam.origin, "target": cam.target, "up": cam.up, "fov": cam.fov}
    if any(cam.principal_point):
        d["principal_point"] = list(cam.principal_point)
    return d


def header_camera(d: dict) -> CameraConfig:
    """The camera of a ``psdr.camera`` header (:func:`camera_header`)."""
    return CameraConfig(origin=tuple(d["origin"]), target=tuple(d["target"]), up=tuple(d["up"]), fov=float(d["fov"]),
                        principal_point=tuple(float(o) for o in d.get("principal_point", (0.0, 0.0))))


def render_view(scene, view: int, spp: int, seed: int = 0, max_depth: int | None = None,
                progress=None) -> np.ndarray:
    """Rendered image (H, W, 3) of camera ``view`` of a :class:`psdr_cli.scene.build.Scene`.

    ``progress(samples_done)`` is called after each pass.
    """
    width, height = scene.resolution
    max_depth = scene.config.max_depth if max_depth is None else max_depth
    sensor = scene.sensors[view]
    total = np.zeros((height, width, 3))
    with dr.suspend_grad():
        for p, n in enumerate(passes_for(spp, width * height)):
            total += render_pass(scene.mi_scene, sensor, width, height, n, max_depth,
                                 pass_seed(seed, view, p, RENDER_STREAM), hide_background=scene.config.hide_background)
            if progress:
                progress(n)
    return (total / spp).astype(np.float32)


def render_views(scene, views, spp: int, seed: int = 0, max_depth: int | None = None) -> list:
    """Rendered images of several cameras ``views`` traced as one wavefront per pass (flat W·H·3
    means on the device, one per view, no AD): the estimator of :func:`render_view`, its passes
    seeded by :func:`psdr_cli.estimators.passes.views_seed`."""
    width, height = scene.resolution
    max_depth = scene.config.max_depth if max_depth is None else max_depth
    sensors = [scene.sensors[v] for v in views]
    total = None
    with dr.suspend_grad():
        for p, n in enumerate(passes_for(spp, width * height * len(views))):
            sums = views_pass(scene.mi_scene, sensors, width, height, n, max_depth,
                              views_seed(seed, views, p, RENDER_STREAM),
                              hide_background=scene.config.hide_background)
            total = sums if total is None else total + sums
        return split_views(total / spp, len(views))


@dataclass
class RenderResult:
    folder: Path
    views: list
    files: list = field(default_factory=list)
    seconds: list = field(default_factory=list)
    spp: int = 0
    resolution: tuple = (0, 0)
    variant: str = ""


def render_experiment(exp: Experiment, spp: int | None = None, views=None, out: Path | None = None,
                      progress=None) -> RenderResult:
    """Render the experiment's views to ``<output>/<name>/render/view_XXX.exr`` (+ PNG previews).

    ``out`` replaces the experiment's ``output`` folder.

    ``progress`` is an optional object with ``start(total_samples)`` and ``advance(n)``.
    """
    spp = exp.estimator.spp if spp is None else spp
    option_spp("--spp", spp, exp.scene.width, exp.scene.height)
    variant = mi.variant()  # activated when the experiment was loaded
    scene = build_scene(exp)
    views = parse_views(views, len(exp.scene.cameras))
    folder = fileio.writable_folder(exp.command_dir("render", out))
    exrs = {v: fileio.check_output_file(folder / f"view_{v:03d}.exr") for v in views}  # before rendering
    for exr in exrs.values():
        fileio.check_output_file(exr.with_suffix(".png"))
    W, H = scene.resolution
    result = RenderResult(folder, views, spp=spp, resolution=(W, H), variant=variant)
    if progress:
        progress.start(len(views) * spp)
    for v in views:
        t0 = time.perf_counter()
        image = render_view(scene, v, spp, seed=exp.seed, progress=progress.advance if progress else None)
        result.seconds.append(time.perf_counter() - t0)
        cam = exp.scene.cameras[v]
        header = {"psdr.experiment": str(exp.file), "psdr.view": str(v), "psdr.spp": str(spp),
                  "psdr.seed": str(exp.seed), "psdr.camera": camera_header(cam)}
        exr = exrs[v]
        fileio.write_rgb_exr(exr, image, header)
        fileio.write_preview(exr.with_suffix(".png"), image)
        result.files.append(exr)
    return result
