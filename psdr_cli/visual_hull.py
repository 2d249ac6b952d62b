"""The visual hull of masked photographs: the initial shape of a reconstruction from a dataset,
with the object's topology (a handle, a hole) before any gradient step.

A point x of the normalised frame is inside the hull when every view that sees it (x in front
of the camera and projected inside the image) has it inside its mask:

    H = { x : ∀ v with π_v(x) ∈ image_v,  m_v(π_v(x)) ≥ ½ },   π_v(x) = K_v R_vᵀ (x − o_v) (pinhole),

sampled on a regular grid over the cube [−b, b]³ and turned into a surface by marching cubes
(scikit-image) at the level ½ of the occupancy; the largest connected part is kept and the
voxel staircase smoothed by Taubin's λ|μ filter (volume-preserving, 10 passes). Points that no
view sees are outside.
"""
from __future__ import annotations

import numpy as np
import trimesh
from skimage.measure import marching_cubes

from .errors import PsdrError


def project(points: np.ndarray, cam_to_world: np.ndarray, fx: float, fy: float, cx: float, cy: float):
    """(pixel column, pixel row, depth) of ``points`` (n, 3) in a pinhole camera with OpenCV
    axes; pixel coordinates with the top-left pixel's centre at (0.5, 0.5)."""
    R, o = cam_to_world[:3, :3], cam_to_world[:3, 3]
    local = (points - o) @ R
    z = local[:, 2]
    safe = np.where(z > 1e-9, z, 1.0)
    return fx * local[:, 0] / safe + cx, fy * local[:, 1] / safe + cy, z


def occupancy(points: np.ndarray, views) -> np.ndarray:
    """Whether each point is inside the hull of ``views`` (each with ``mask`` (H, W) in [0, 1],
    ``cam_to_world`` in the normalised frame and pinhole intrinsics at the mask's resolution)."""
    inside = np.ones(len(points), bool)
    seen = np.zeros(len(points), bool)
    for view in views:
        u, v, z = project(points, view.cam_to_world, view.fx, view.fy, view.cx, view.cy)
        h, w = view.mask.shape
        visible = (z > 1e-9) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
        col = np.clip(u.astype(np.int64), 0, w - 1)
        row = np.clip(v.astype(np.int64), 0, h - 1)
        inside &= ~visible | (view.mask[row, col] >= 0.5)
        seen |= visible
    return inside & seen


def visual_hull(views, bound: float = 1.5, resolution: int = 72):
    """(V, F) of the hull surface of ``views`` over [−bound, bound]³ on a ``resolution``³ grid."""
    axis = np.linspace(-bound, bound, resolution)
    grid = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)
    occ = occupancy(grid, views).reshape((resolution,) * 3).astype(np.float32)
    if occ.sum() < 8:
        raise PsdrError("the masks' visual hull is empty: no point is inside every mask that sees it "
                        "(check that the masks are white on the object and that the cameras are right)")
    padded = np.pad(occ, 1)
    step = axis[1] - axis[0]
    V, F, _, _ = marching_cubes(padded, 0.5, spacing=(step, step, step))
    V = V - bound - step  # the padding shifts the grid by one cell
    parts = trimesh.Trimesh(V, F, process=True).split(only_watertight=False)
    largest = max(parts, key=lambda m: len(m.faces))
    if largest.volume < 0:  # outward normals: counter-clockwise seen from outside
        largest.invert()
    trimesh.smoothing.filter_taubin(largest, iterations=10)
    return np.asarray(largest.vertices, np.float64), np.asarray(largest.faces, np.int64)
