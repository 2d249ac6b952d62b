"""Regular-grid guide (Zhang et al. 2020), the baseline the Kd-tree is compared against.

The primary-sample space is cut into nx × ny × nz equal cells; a cell's value is the mean of the
target F̃ at ``samples_per_cell`` uniform points inside it, and the guide is piecewise constant
(docs/theory.md §5):

    g(u) = ε + (1 − ε) · value(cell(u)) / Σ_cells (value · volume).

Parameters (experiment keys)
----------------------------
Used when ``estimator.guiding`` is ``grid`` (``auto`` never picks it):

``estimator.grid.resolution`` ([nx, ny, nz], default [64, 8, 8])
    Cells over (u1, u2.x, u2.y); at most 2²² cells.
``estimator.grid.samples_per_cell`` (int ≥ 1, default 64)
    Target evaluations per cell; cells × samples_per_cell ≤ 2²⁸.
``estimator.guide_epsilon`` (float in [0, 1], default 0.05)
    Uniform share ε.
"""
from __future__ import annotations

import time

import drjit as dr
import mitsuba as mi
import numpy as np

from .guide import Guide, GuideKind, GuideStats


class GridGuide(Guide):
    kind = "grid"

    def __init__(self, resolution, values, epsilon, stats):
        self.resolution = tuple(int(r) for r in resolution)
        nx, ny, nz = self.resolution
        i, j, k = np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij")
        # cell l = i + nx (j + ny k)
        idx = np.stack([a.transpose(2, 1, 0).ravel() for a in (i, j, k)], 1).astype(np.float64)
        res = np.array(self.resolution, np.float64)
        corners = np.repeat(np.asarray(values, np.float64)[:, None], 8, axis=1)
        super().__init__(idx / res, (idx + 1) / res, corners, epsilon, stats)

    def leaf_of(self, u: mi.Point3f) -> mi.UInt32:
        nx, ny, nz = self.resolution
        i = dr.minimum(mi.UInt32(u.x * nx), nx - 1)
        j = dr.minimum(mi.UInt32(u.y * ny), ny - 1)
        k = dr.minimum(mi.UInt32(u.z * nz), nz - 1)
        return i + nx * (j + ny * k)

    def leaf_of_np(self, u: np.ndarray) -> np.ndarray:
        res = np.array(self.resolution)
        ijk = np.minimum((u * res).astype(np.int64), res - 1)
        return ijk[:, 0] + res[0] * (ijk[:, 1] + res[1] * ijk[:, 2])

    def memory_bytes(self) -> int:
        """A grid needs only one value and one CDF entry per cell."""
        return 8 * len(self.mass)


def build_grid(target, resolution=(64, 8, 8), samples_per_cell: int = 16, epsilon: float = 0.01,
               seed: int = 0) -> GridGuide:
    """Grid guide of ``target`` (numpy u (N,3) → F̃ ≥ 0 (N,))."""
    t0 = time.perf_counter()
    rng = np.random.default_rng(seed)
    nx, ny, nz = resolution
    cells = nx * ny * nz
    l = np.arange(cells)
    idx = np.stack([l % nx, (l // nx) % ny, l // (nx * ny)], 1).astype(np.float64)
    u = (idx[:, None, :] + rng.random((cells, samples_per_cell, 3))) / np.array(resolution, np.float64)
    values = np.asarray(target(u.reshape(-1, 3)), np.float64).reshape(cells, samples_per_cell).mean(1)
    stats = GuideStats("grid", max_depth=0, evaluations=cells * samples_per_cell, intervals=1)
    guide = GridGuide(resolution, values, epsilon, stats)
    stats.memory_bytes = guide.memory_bytes()
    stats.build_seconds = time.perf_counter() - t0
    return guide


def build_grid_guide(target, breaks, estimator, seed: int, pixels: int) -> GridGuide:
    """A grid guide of ``estimator.grid``'s resolution and samples per cell (:class:`~.guide.GuideKind`;
    the breakpoints and the film's size are not used)."""
    g = estimator.grid
    return build_grid(target, g.resolution, g.samples_per_cell, estimator.guide_epsilon, seed)


KIND = GuideKind("grid", build_grid_guide)
