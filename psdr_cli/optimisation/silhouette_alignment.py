"""Camera poses registered to the masks before the visual hull is carved (a run that refines its
cameras: ``optimize.cameras``).

Poses off by a fraction of a degree make the masks disagree: the hull, carved with the margin
the disagreement needs (:mod:`psdr_cli.target_sources.visual_hull`), is fat by that margin on
every side, and the loop starts from it and from the wrong poses. Before carving, each view is
therefore turned until its mask fits inside the silhouette of the hull of the other views
(silhouette coherence):

1. carve at the current poses, keeping for each grid point x its largest mask distance δ₁(x) over
   the views that see it, the view v₁(x) it comes from and the second largest δ₂(x); the exact
   hull of the views other than v is then H₋ᵥ = { x : (δ₂(x) if v₁(x) = v else δ₁(x)) ≤ 0 }
   (≤ m in the rounds carved m pixels wide, below);
2. draw H₋ᵥ in view v (each voxel as its centre and its eight corners) and find the image shift
   s = (Δu, Δv) that puts v's mask inside that silhouette: the least mean of min(D(x − s),
   :data:`TRUNCATE_PX`) over the pixels x of the mask's outline that lie within
   :data:`TRUNCATE_PX` of it as given (D: the distance to the silhouette; a thin part the others'
   wrong poses carved away neither pulls nor weighs); the mask fits alike at every shift of a
   region about a pixel wide (the drawn voxels cover whole pixels), so s is the centre (mean) of
   the shifts within :data:`TIE_PX` of the least, where the mask sits centred; searched on a grid
   of :data:`COARSE_STEP` pixels within ±:data:`MAX_SHIFT_PX`, then of :data:`SEARCH_STEP` around
   the coarse centre;
3. turn view v about its own centre so that its image moves by s: a tilt of Δv/f_y and a pan of
   −Δu/f_x in OpenCV's camera axes (x right, y down), i.e. the correction r_v += (−Δv/f_y, Δu/f_x, 0)
   of :mod:`psdr_cli.optimisation.camera_refinement` (Mitsuba's camera axes: x left, y up);
4. project the corrections onto the complement of the gauge (the seven similarity motions of
   the whole capture, as the loop does after every step), so the capture keeps its mean pose.

At most :data:`ROUNDS` rounds, fewer once every shift is below :data:`SETTLED_PX` or a round's
turn does not make the masks disagree less (the mean width of the band of each mask that the exact
hull of all views leaves uncovered); the result is the poses, the given ones first, whose masks
disagree least, so a registration that does not help leaves the poses as given (exact poses: the
centres are a fraction of a pixel off zero, by the pixel grids, and turning by them does not lower
the disagreement). Poses off by a few pixels carve each view's thin parts out of the others' exact
hulls, and those rounds keep the given poses too; whenever they do, the rounds are run again from
the given poses with H₋ᵥ carved :data:`COARSE_MARGINS` wide of the masks in the first ones (a
silhouette fat by a margin on every side still has the mask centred inside it where the poses
agree), exactly after that, with as many more rounds as margins, and the poses whose masks
disagree least of both are kept (given poses on a tie). A view whose fitting shifts reach the
search's edge (±:data:`MAX_SHIFT_PX`, a margin wider in a round carved with one), or whose others'
hull does not reach its image, is not moved in that round. The shifts are searched within one
coarse step of the coarse centre, which may leave them up to about 0.1 px short of the centre of a
region wider than that search (a pixel). The corrections are the loop's starting corrections (its
Adam entries start there), so the hull, the loop and ``cameras.json`` see the same poses. A shift
across the image is the part of a pose error a silhouette shows best; the turn about the optical
axis, the distance and the split between a turn and a sideways move are left to the loop.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np
from scipy import ndimage
from scipy.spatial.transform import Rotation

from ..target_sources.visual_hull import carving_grid, mask_distances, pixel, project
from .camera_refinement import OPENCV_FLIP, camera_frames, gauge_basis, without_gauge

#: Rounds of registration and carving at most.
ROUNDS = 4

#: Shift (pixels) below which every view is taken as registered.
SETTLED_PX = 0.05

#: The largest shift searched (pixels; a margin wider against hulls carved with one): a view whose
#: fitting shifts reach this edge is not moved.
MAX_SHIFT_PX = 4.0

#: Steps (pixels) of the coarse search and of the fine one, within one coarse step of its centre.
COARSE_STEP, SEARCH_STEP = 0.5, 0.1

#: Distance (pixels) at which an outline pixel's cost stops growing: a part of the mask that the
#: other views' hull lost (a thin part cut by their wrong poses) weighs alike at every shift.
TRUNCATE_PX = 2.0

#: Mean outline distance (pixels) within which two shifts fit a mask alike.
TIE_PX = 0.02

#: Margins (pixels) of the other views' hulls in the first rounds of the second registration,
#: run when the rounds against the exact hulls keep the given poses (poses off by a few pixels
#: carve each view's thin parts out of the others' exact hull).
COARSE_MARGINS = (2.0, 1.0)


def view_frames(views):
    """(origins o_v, Mitsuba camera axes Q_v, look-at point c, distances d_v) of ``views``
    (OpenCV ``cam_to_world`` in the normalised frame), as :class:`CameraCorrections` has them."""
    return camera_frames(np.stack([np.asarray(v.cam_to_world, np.float64) @ OPENCV_FLIP for v in views]))


def corrected(cam_to_world: np.ndarray, axes: np.ndarray, distance: float, r: np.ndarray, tau: np.ndarray):
    """The OpenCV camera-to-world of the loop's correction (r, τ) of one view:
    [R(Q r) R⁰ | o + d Q τ] (:mod:`.camera_refinement`)."""
    M = np.array(cam_to_world, np.float64)
    out = M.copy()
    out[:3, :3] = Rotation.from_rotvec(axes @ r).as_matrix() @ M[:3, :3]
    out[:3, 3] = M[:3, 3] + distance * (axes @ tau)
    return out


def silhouette(points: np.ndarray, step: float, view) -> np.ndarray:
    """(H, W) bool: the pixels of ``view`` that voxels centred at ``points`` (``step`` wide) cover,
    each voxel drawn as its eight corners and its centre."""
    corners = 0.5 * step * np.array([[a, b, c] for a in (-1, 1) for b in (-1, 1) for c in (-1, 1)] + [[0, 0, 0]])
    samples = (points[:, None, :] + corners).reshape(-1, 3)
    u, v, z = project(samples, view.cam_to_world, view.fx, view.fy, view.cx, view.cy)
    shape = view.mask.shape
    ok = (z > 1e-9) & (u >= 0) & (u < shape[1]) & (v >= 0) & (v < shape[0])
    drawn = np.zeros(shape, bool)
    drawn[pixel(u[ok], v[ok], shape)] = True
    return drawn


def fitting_shift(mask: np.ndarray, outline: np.ndarray, drawn: np.ndarray, bound: float = MAX_SHIFT_PX) -> np.ndarray:
    """(Δu, Δv): the image shift of the silhouette ``drawn`` that puts ``mask``'s ``outline``
    centred inside it, or leaves it least outside (module docstring, step 2), searched within
    ±``bound`` pixels; NaN when the shifts that fit reach the search's edge."""
    distance = np.minimum(ndimage.distance_transform_edt(~drawn), TRUNCATE_PX)
    rows, cols = np.nonzero(outline & (distance < TRUNCATE_PX))  # parts the others' hull lost do not pull
    if len(rows) == 0:
        return np.full(2, np.nan)
    coarse = np.arange(-bound, bound + 1e-9, COARSE_STEP)
    near = best_fits(distance, rows, cols, *np.meshgrid(coarse, coarse))
    if np.abs(near).max() >= bound:
        return np.full(2, np.nan)
    centre = near.mean(0)
    fine = np.arange(-COARSE_STEP, COARSE_STEP + 1e-9, SEARCH_STEP)
    du, dv = np.meshgrid(fine, fine)
    return best_fits(distance, rows, cols, du + centre[0], dv + centre[1]).mean(0)


def best_fits(distance: np.ndarray, rows, cols, du, dv) -> np.ndarray:
    """(k, 2): the shifts among (``du``, ``dv``) whose mean ``distance`` over the outline pixels
    (``rows``, ``cols``) moved back by them is within :data:`TIE_PX` of the least."""
    du, dv = du.ravel(), dv.ravel()
    at = [(rows[None, :] - dv[:, None]).ravel(), (cols[None, :] - du[:, None]).ravel()]
    cost = ndimage.map_coordinates(distance, at, order=1, mode="nearest").reshape(len(du), len(rows)).mean(1)
    near = cost <= cost.min() + TIE_PX
    return np.stack([du[near], dv[near]], 1)


def silhouette_shifts(views, grid: np.ndarray, step: float, margin: float = 0.0) -> tuple:
    """(shifts, band, δ₂): the (n, 2) image shifts (Δu, Δv) in pixels that fit each view's mask
    inside the silhouette of the hull of the other views carved ``margin`` pixels wide of their
    masks (0: exact; module docstring, steps 1–2), NaN where there is none; the disagreement of
    the masks, the mean over the views of the width (pixels) of the band of the mask that the
    exact hull of all views leaves uncovered (|mask ∖ drawn| / |outline|); and each grid point's
    second largest mask distance."""
    first, owner, second = mask_distances(grid, views)
    hull = grid[(owner >= 0) & (first <= 0)]
    shifts, bands = np.full((len(views), 2), np.nan), []
    for i, view in enumerate(views):
        mask = None if view.mask is None else view.mask >= 0.5
        if mask is None or not mask.any():
            continue
        outline = mask & ~ndimage.binary_erosion(mask)
        bands.append((mask & ~silhouette(hull, step, view)).sum() / outline.sum())
        others = np.where(owner == i, second, np.where(owner >= 0, first, np.inf))
        inside = (others <= margin) & (others > -np.inf)
        drawn = silhouette(grid[inside], step, view) if inside.any() else None
        if drawn is not None and drawn.any():
            shifts[i] = fitting_shift(mask, outline, drawn, MAX_SHIFT_PX + margin)
    return shifts, float(np.mean(bands)) if bands else 0.0, np.where(owner >= 0, second, np.inf)


def aligned_corrections(views, rotation: bool = True, translation: bool = True, max_rotation: float = np.inf,
                        rounds: int = ROUNDS) -> dict:
    """The loop's starting corrections ``{"camera_rotation": (n, 3), "camera_translation": (n, 3)}``
    (radians; camera distances) that make ``views``' masks agree (module docstring): of the
    poses the rounds pass through (the given ones first), those whose masks disagree least
    (:func:`registration_rounds` against the exact hulls; when they keep the given poses, again
    with the first rounds against hulls carved :data:`COARSE_MARGINS` wide, the better of the
    two); zeros when ``rotation`` is not refined (a shift is turned into a rotation). A view
    stops turning before its correction would pass half of ``max_rotation`` (radians; the loop's
    own bound stays clear). After the first carving only the grid points that at most one view
    sees farther than ``reach`` pixels from its mask are carved again: the most the rounds' turns
    can move an image (each within its search bounds along both axes), a pixel's diagonal (the
    distances are read at pixels) and the widest margin, with a fifth more for the magnification
    off the image's centre and the gauge projection; the others stay outside every hull."""
    n = len(views)
    given = {"camera_rotation": np.zeros((n, 3)), "camera_translation": np.zeros((n, 3))}
    if not rotation or n < 2:
        return given
    grid, step = carving_grid(views)
    shifts, least, second = silhouette_shifts(views, grid, step)
    moved = np.sqrt(2) * ((rounds + len(COARSE_MARGINS)) * MAX_SHIFT_PX + sum(COARSE_MARGINS))
    reach = 1.2 * (moved + np.sqrt(2) + max(COARSE_MARGINS))
    grid = grid[second <= reach]
    best, least = registration_rounds(views, grid, step, shifts, least, (), rounds, translation=translation,
                                      max_rotation=max_rotation)
    if any(np.any(v) for v in best.values()):
        return best
    coarse, fewer = registration_rounds(views, grid, step, None, least, COARSE_MARGINS, rounds + len(COARSE_MARGINS),
                                        translation=translation, max_rotation=max_rotation)
    return coarse if fewer < least else best


def registration_rounds(views, grid: np.ndarray, step: float, shifts, band: float, margins: tuple, rounds: int, *,
                        translation: bool, max_rotation: float) -> tuple:
    """(corrections, band): of the poses ``rounds`` rounds pass through from the given ones,
    those whose masks disagree least (:func:`silhouette_shifts`); round k registers against the
    other views' hulls carved ``margins[k]`` pixels wide (0 past the end); the rounds stop once
    every shift is below :data:`SETTLED_PX` or a turn does not lower the disagreement. ``shifts``
    and ``band``: the given poses' against the exact hulls when known (``margins`` empty), else
    None and any."""
    n = len(views)
    r, tau = np.zeros((n, 3)), np.zeros((n, 3))
    origins, axes, centre, distances = view_frames(views)
    G = gauge_basis(axes, origins, centre, distances, True, translation)
    fx, fy = np.array([v.fx for v in views]), np.array([v.fy for v in views])
    for k in range(rounds + 1):
        now = {"camera_rotation": r.copy(), "camera_translation": tau.copy()}
        margin = margins[k] if k < len(margins) else 0.0
        if k > 0 or shifts is None:
            shifts, band, _ = silhouette_shifts(aligned_views(views, now), grid, step, margin)
        if k > 0 and band >= least:  # the last turn did not make the masks agree better
            break
        best, least = now, band
        turned = r.copy()
        turned[:, 0] -= np.nan_to_num(shifts[:, 1]) / fy
        turned[:, 1] += np.nan_to_num(shifts[:, 0]) / fx
        usable = np.isfinite(shifts).all(1) & (np.linalg.norm(turned, axis=1) <= 0.5 * max_rotation)
        if k == rounds or not usable.any() or np.abs(shifts[usable]).max() < SETTLED_PX:
            break
        r[usable] = turned[usable]
        x = np.concatenate([r.ravel()] + ([tau.ravel()] if translation else []))
        x = without_gauge(x, G, np.ones(len(x), bool))
        r = x[:3 * n].reshape(n, 3)
        if translation:
            tau = x[3 * n:].reshape(n, 3)
    return best, least


def aligned_views(views, values: dict) -> list:
    """``views`` with the cameras of the corrections ``values`` (:func:`aligned_corrections`)."""
    _, axes, _, distances = view_frames(views)
    return [replace(v, cam_to_world=corrected(v.cam_to_world, axes[i], distances[i], values["camera_rotation"][i],
                                              values["camera_translation"][i])) for i, v in enumerate(views)]
