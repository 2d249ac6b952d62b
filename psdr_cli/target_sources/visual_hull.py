"""The visual hull of masked photographs: the initial shape of a reconstruction from a dataset,
with the object's topology (a handle, a hole) before any gradient step.

A point x of the normalised frame is inside the hull when every view that sees it (x in front
of the camera and projected inside the image) has it inside its mask:

    H = { x : ∀ v with π_v(x) ∈ image_v,  m_v(π_v(x)) ≥ ½ },   π_v(x) = K_v R_vᵀ (x − o_v) (pinhole),

sampled on a regular grid over the cube [−b, b]³ whose cell is about one pixel of the masks at
the object (:func:`grid_resolution`: the median over views of |o_v|/f_v, the footprint of a pixel
at the look-at point, the origin; between :data:`MIN_RESOLUTION` and :data:`MAX_RESOLUTION` cells
a side), so that a part a few pixels wide survives, and turned into a surface by marching cubes
(scikit-image) at the level ½ of the occupancy; the largest connected part is kept and the
voxel staircase smoothed by Taubin's λ|μ filter (volume-preserving, 10 passes). Points that no
view sees are outside.

Cameras that are slightly wrong (or masks that are slightly off) make the masks disagree: the
cones of the true silhouettes no longer meet on the object, and H loses its thin parts, which a
reconstruction does not grow back. The hull is therefore carved with a margin m (pixels):

    H_m = { x : max_{v sees x} δ_v(π_v(x)) ≤ m },   δ_v the distance (pixels) to view v's mask,

with the smallest m of :data:`MARGINS` whose hull explains the masks: in 90 % of the views the
mask's pixels farther than 1.5 voxel footprints from the hull's projection (the grid's own
resolution forgives the rest) number at most :data:`LOST_WIDTH` times the mask's perimeter (a
band that thin on average). Consistent masks give m = 0, H_0 = H. A run that refines its cameras
registers their poses to the masks first (:mod:`psdr_cli.optimisation.silhouette_alignment`), so
that its hull usually needs no margin.
"""
from __future__ import annotations

import warnings

import numpy as np
import trimesh
from scipy import ndimage
from skimage.measure import marching_cubes

from ..errors import PsdrError, PsdrWarning

#: The margins tried (pixels of the masks), smallest first.
MARGINS = (0, 1, 2, 3, 4, 6, 8)

#: The mean width (pixels) of the band of a mask the hull may leave uncovered (in 90 % of the views).
LOST_WIDTH = 0.1

#: Fewest and most grid points a side of the carving grid (:func:`grid_resolution`).
MIN_RESOLUTION, MAX_RESOLUTION = 72, 128

#: Views checked for coverage (evenly spread; all of them when there are fewer).
COVERAGE_VIEWS = 24


def project(points: np.ndarray, cam_to_world: np.ndarray, fx: float, fy: float, cx: float, cy: float):
    """(pixel column, pixel row, depth) of ``points`` (n, 3) in a pinhole camera with OpenCV
    axes; pixel coordinates with the top-left pixel's centre at (0.5, 0.5)."""
    R, o = cam_to_world[:3, :3], cam_to_world[:3, 3]
    local = (points - o) @ R
    z = local[:, 2]
    safe = np.where(z > 1e-9, z, 1.0)
    return fx * local[:, 0] / safe + cx, fy * local[:, 1] / safe + cy, z


def pixel(u, v, shape):
    """(row, column) indices of the pixels containing image points (u, v), clamped to ``shape``."""
    h, w = shape
    return np.clip(v.astype(np.int64), 0, h - 1), np.clip(u.astype(np.int64), 0, w - 1)


def mask_distance(points: np.ndarray, views) -> np.ndarray:
    """max over the views that see each point (in front, projected inside the image) of the
    distance in pixels from its pixel to the view's mask (0 inside); +∞ where no view sees it.
    ``views``: each with ``mask`` (H, W) in [0, 1], ``cam_to_world`` in the normalised frame and
    pinhole intrinsics at the mask's resolution."""
    first, owner, _ = mask_distances(points, views)
    return np.where(owner >= 0, first, np.inf)


def mask_distances(points: np.ndarray, views) -> tuple:
    """(δ₁, v₁, δ₂) per point: the largest distance (pixels) to a mask over the views that see it
    (:func:`mask_distance`), the index of that view, and the second largest; v₁ = −1 and
    δ₁ = δ₂ = −∞ where no view sees the point, δ₂ = −∞ where one view does."""
    first = np.full(len(points), -np.inf)
    second = np.full(len(points), -np.inf)
    owner = np.full(len(points), -1, np.int64)
    for i, view in enumerate(views):
        u, v, z = project(points, view.cam_to_world, view.fx, view.fy, view.cx, view.cy)
        h, w = view.mask.shape
        visible = (z > 1e-9) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
        outside = view.mask < 0.5
        distance = ndimage.distance_transform_edt(outside) if not outside.all() else np.full(outside.shape, np.inf)
        d = np.where(visible, distance[pixel(u, v, (h, w))], -np.inf)
        bigger = d > first
        second = np.where(bigger, first, np.maximum(second, d))
        owner = np.where(bigger, i, owner)
        first = np.where(bigger, d, first)
    return first, owner, second


def lost_width(points: np.ndarray, step: float, view) -> float:
    """The pixels of ``view``'s mask farther than 1.5 voxel footprints (``step`` wide, at the
    points' median depth) from the projection of voxels centred at ``points``, over the mask's
    perimeter (pixels): the mean width of the band the voxels leave uncovered."""
    corners = 0.3 * step * np.array([[a, b, c] for a in (-1, 1) for b in (-1, 1) for c in (-1, 1)])
    samples = (points[:, None, :] + corners).reshape(-1, 3)
    u, v, z = project(samples, view.cam_to_world, view.fx, view.fy, view.cx, view.cy)
    shape = view.mask.shape
    ok = (z > 1e-9) & (u >= 0) & (u < shape[1]) & (v >= 0) & (v < shape[0])
    mask = view.mask >= 0.5
    if not mask.any() or not ok.any():
        return 0.0 if not mask.any() else np.inf
    drawn = np.zeros(shape, bool)
    drawn[pixel(u[ok], v[ok], shape)] = True
    reach = 1.5 * step * view.fx / float(np.median(z[ok]))
    near = ndimage.distance_transform_edt(~drawn) <= reach
    perimeter = (mask & ~ndimage.binary_erosion(mask)).sum()
    return float((mask & ~near).sum() / max(perimeter, 1))


def hull_margin(grid: np.ndarray, distance: np.ndarray, step: float, views) -> tuple:
    """(margin, explained): the smallest margin of :data:`MARGINS` whose hull leaves at most
    :data:`LOST_WIDTH` of the masks uncovered (:func:`lost_width`) in 90 % of (up to
    :data:`COVERAGE_VIEWS`) views, explained True; the largest, explained False, when none does."""
    checked = [views[i] for i in np.unique(np.linspace(0, len(views) - 1, COVERAGE_VIEWS).round().astype(int))]
    for margin in MARGINS:
        inside = grid[distance <= margin]
        widths = [lost_width(inside, step, view) for view in checked] if len(inside) else [np.inf]
        if np.percentile(np.minimum(widths, 1e30), 90) <= LOST_WIDTH:
            return margin, True
    return MARGINS[-1], False


def grid_resolution(views, bound: float) -> int:
    """Grid points a side over [−bound, bound] for cells of one pixel at the origin: 2·bound / h + 1
    with h the median of |o_v| / f_v over the views (camera centre o_v, focal length f_v in
    pixels), clamped to [:data:`MIN_RESOLUTION`, :data:`MAX_RESOLUTION`]."""
    footprint = float(np.median([np.linalg.norm(v.cam_to_world[:3, 3]) / v.fx for v in views]))
    wanted = int(np.ceil(2 * bound / max(footprint, 1e-9))) + 1
    return int(np.clip(wanted, MIN_RESOLUTION, MAX_RESOLUTION))


def carving_grid(views, bound: float = 1.5, resolution: int | None = None) -> tuple:
    """(points (m, 3), cell width): the regular grid of ``resolution`` points a side over
    [−bound, bound]³ (None: :func:`grid_resolution`)."""
    resolution = grid_resolution(views, bound) if resolution is None else resolution
    axis = np.linspace(-bound, bound, resolution)
    return np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3), axis[1] - axis[0]


def visual_hull(views, bound: float = 1.5, resolution: int | None = None, margin: float | None = None):
    """(V, F) of the hull surface H_m of ``views`` over [−bound, bound]³ on a ``resolution``³
    grid (None: :func:`grid_resolution`); ``margin`` m in pixels, or None: the smallest that
    explains the masks (module docstring; a warning says when it is not 0)."""
    resolution = grid_resolution(views, bound) if resolution is None else resolution
    grid, step = carving_grid(views, bound, resolution)
    distance = mask_distance(grid, views)
    if margin is None:
        margin, explained = hull_margin(grid, distance, step, views)
        if margin > 0:
            about = "about" if explained else "more than"
            warnings.warn(f"the masks disagree by {about} {margin:g} px (camera poses or masks slightly off): the "
                          f"visual hull is carved {margin:g} px wide of them so that it keeps the object's thin parts",
                          PsdrWarning, stacklevel=2)
    occ = (distance <= margin).reshape((resolution,) * 3).astype(np.float32)
    if occ.sum() < 8:
        raise PsdrError("the masks' visual hull is empty: no point is inside every mask that sees it "
                        "(check that the masks are white on the object and that the cameras are right)")
    padded = np.pad(occ, 1)
    V, F, _, _ = marching_cubes(padded, 0.5, spacing=(step, step, step))
    V = V - bound - step  # the padding shifts the grid by one cell
    parts = trimesh.Trimesh(V, F, process=True).split(only_watertight=False)
    largest = max(parts, key=lambda m: len(m.faces))
    if largest.volume < 0:  # outward normals: counter-clockwise seen from outside
        largest.invert()
    trimesh.smoothing.filter_taubin(largest, iterations=10)
    return np.asarray(largest.vertices, np.float64), np.asarray(largest.faces, np.int64)
