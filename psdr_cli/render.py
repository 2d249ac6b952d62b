"""Forward rendering of camera views with the interior estimator.

Pixels use a box filter: sample j of pixel (x, y) is the film point ((x, y) + ξ_j) / (W, H) with ξ_j
uniform in [0,1)², and the pixel value is the mean of its ``spp`` radiance samples. Large sample
counts run in passes of at most ``max_lanes`` paths so memory stays bounded; each pass is reduced
per pixel with ``dr.block_sum`` (deterministic, unlike atomic scatter-adds).
"""
from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi
import numpy as np

from .estimators import interior

#: Upper bound on the number of paths traced in one pass.
MAX_LANES = 1 << 21


def pass_seed(seed: int, view: int, pass_index: int, stream: int = 0) -> int:
    """A 32-bit seed per (experiment seed, view, pass, stream), decorrelated by a hash."""
    h = (seed * 0x9E3779B1 + view * 0x85EBCA77 + pass_index * 0xC2B2AE3D + stream * 0x27D4EB2F) & 0xFFFFFFFF
    h ^= h >> 16
    h = (h * 0x7FEB352D) & 0xFFFFFFFF
    h ^= h >> 15
    return h


def make_sampler(seed: int, lanes: int) -> mi.Sampler:
    """Independent sampler for ``lanes`` parallel paths; the seed is opaque so kernels are reused."""
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(dr.opaque(mi.UInt32, seed), lanes)
    return sampler


def passes_for(spp: int, pixels: int, max_lanes: int = MAX_LANES) -> list[int]:
    """Split ``spp`` samples per pixel into passes of at most ``max_lanes`` paths each."""
    per_pass = max(1, min(spp, max_lanes // max(pixels, 1)))
    n = math.ceil(spp / per_pass)
    base, extra = divmod(spp, n)
    return [base + (1 if i < extra else 0) for i in range(n)]


def camera_rays(sensor: mi.Sensor, sampler: mi.Sampler, width: int, height: int, spp: int):
    """One ray per (pixel, sample), pixel-major: lane i belongs to pixel i // spp."""
    idx = dr.arange(mi.UInt32, width * height * spp)
    pixel = idx // dr.opaque(mi.UInt32, spp)
    pos = mi.Point2f(mi.Float(pixel % width), mi.Float(pixel // width)) + sampler.next_2d()
    film_uv = pos / mi.ScalarVector2f(width, height)
    ray, weight = sensor.sample_ray(0.0, sampler.next_1d(), film_uv, mi.Point2f(0.5))
    return ray, weight


def render_pass(scene: mi.Scene, sensor: mi.Sensor, width: int, height: int, spp: int,
                max_depth: int, seed: int) -> np.ndarray:
    """Sum over ``spp`` samples of every pixel, as a (H, W, 3) float64 array."""
    sampler = make_sampler(seed, width * height * spp)
    ray, weight = camera_rays(sensor, sampler, width, height, spp)
    L = weight * interior.radiance(scene, sampler, ray, max_depth)
    sums = [dr.block_sum(L[c], spp) for c in range(3)]
    dr.eval(sums)
    return np.stack([np.asarray(s, np.float64) for s in sums], axis=-1).reshape(height, width, 3)


def render_view(scene, view: int, spp: int, seed: int = 0, max_depth: int | None = None,
                progress=None) -> np.ndarray:
    """Rendered image (H, W, 3) of camera ``view`` of a :class:`psdr_cli.scene.Scene`.

    ``progress(samples_done)`` is called after each pass.
    """
    width, height = scene.resolution
    max_depth = scene.config.max_depth if max_depth is None else max_depth
    sensor = scene.sensors[view]
    total = np.zeros((height, width, 3))
    with dr.suspend_grad():
        for p, n in enumerate(passes_for(spp, width * height)):
            total += render_pass(scene.mi_scene, sensor, width, height, n, max_depth,
                                 pass_seed(seed, view, p))
            if progress:
                progress(n)
    return (total / spp).astype(np.float32)
