"""Samples in passes: independent samplers, per-pass seeds, and the split of a sample count.

Large sample counts run in passes so that memory stays bounded: ``spp`` samples per pixel of an
image with P pixels are split into n passes of at most L paths (lanes) each,

    n = max(min_passes, ⌈spp / ⌊L / P⌋⌉)   (at most spp),

with the counts of the passes differing by at most one. Every pass gets its own seed, a hash of
(experiment seed, view, pass, stream), so passes, views and terms never share random numbers.
Passes traced together as one wavefront (several views of a mini-batch, or several passes of one
view in forward mode) share one seed (:func:`views_seed`) and take their samples from different
lanes of its sampler, so they never share random numbers either.
"""
from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi

#: Upper bound on the paths of one primal (rendering) pass.
MAX_LANES = 1 << 21
#: Upper bound on the lanes of one differentiable pass (AD graphs are larger than primal ones).
AD_LANES = 1 << 20


def pass_seed(seed: int, view: int, pass_index: int, stream: int = 0) -> int:
    """A 32-bit seed per (experiment seed, view, pass, stream), decorrelated by a hash."""
    h = (seed * 0x9E3779B1 + view * 0x85EBCA77 + pass_index * 0xC2B2AE3D + stream * 0x27D4EB2F) & 0xFFFFFFFF
    h ^= h >> 16
    h = (h * 0x7FEB352D) & 0xFFFFFFFF
    h ^= h >> 15
    return h


def views_seed(seed: int, views, pass_index: int, stream: int = 0) -> int:
    """The seed of a pass that traces several ``views`` in one wavefront (views of a mini-batch, or
    one view repeated for several passes, ``pass_index`` the first of them): :func:`pass_seed` with
    the views folded into one key (≥ 2^20, so that it names no single view; one view: its own seed)."""
    if len(views) == 1:
        return pass_seed(seed, views[0], pass_index, stream)
    key = 0
    for v in views:
        key = (key * 0x01000193 + v + 1) & 0xFFFFFFFF
    return pass_seed(seed, key | 0x100000, pass_index, stream)


def make_sampler(seed, lanes: int) -> mi.Sampler:
    """Independent sampler for ``lanes`` parallel paths; the seed (an int, or a ``mi.UInt32`` of
    one entry: an input of a frozen function) is opaque so kernels are reused."""
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(seed if isinstance(seed, mi.UInt32) else dr.opaque(mi.UInt32, seed), lanes)
    return sampler


def passes_for(spp: int, pixels: int, max_lanes: int = MAX_LANES, min_passes: int = 1) -> list[int]:
    """Samples per pixel of each pass (see the module docstring)."""
    per_pass = max(1, min(spp, max_lanes // max(pixels, 1)))
    n = min(spp, max(min_passes, math.ceil(spp / per_pass)))
    base, extra = divmod(spp, n)
    return [base + (1 if i < extra else 0) for i in range(n)]
