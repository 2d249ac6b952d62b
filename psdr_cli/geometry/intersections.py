"""Intersection curves of triangle meshes that pierce each other (or one mesh's separate shells).

Where two surfaces cross, the image and the shading are discontinuous along their intersection
curve (the surface normal jumps there), and that curve moves with θ although it lies on no mesh
edge. This module finds the curve as triangle–triangle intersection segments (numpy, rebuilt
whenever the geometry moves) and evaluates their end points differentiably.

For triangles A and B with planes (c, n = (d − c) × (e − c)), each end point of the segment A ∩ B
is where an edge (a, b) of one triangle crosses the plane of the other:

    p = a + t (b − a),   t = ((c − a)·n) / ((b − a)·n).

Both end points lie on the line plane(A) ∩ plane(B) for every θ, so the component of the
velocity of p normal to the curve (the only one a boundary integral sees) is exact; the
tangential component (sliding along the curve) does not matter.

An intersection curve of two opaque solids is a concave crease of the union's surface: every line
through it enters a solid, so it bounds visibility of no boundary segment and only the primary
(camera) term needs it. Pairs of triangles that share a (welded) vertex are adjacent, not
intersecting, and are skipped; touching triangles (a vertex exactly on the other plane) give
segments of zero length, which are dropped.
"""
from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from ..support.jitarray import jit_array
from .topology import weld

#: A box larger than this many broad-phase cells along an axis is compared with every box
#: directly instead of being put into the grid (:func:`overlapping_pairs`).
LARGE_BOX_CELLS = 8

#: Rows of a dense large-box comparison processed at once (memory of the test).
CHUNK = 512


@dataclass
class Segments:
    """Intersection segments; every array has one row per segment.

    ``ends``: (n, 2, 5) vertex ids per end point: edge (a, b) and the plane triangle (c, d, e), all
    in the concatenated vertex numbering of the meshes passed to :func:`intersection_segments`.
    ``mesh``: (n, 2) mesh index of the two triangles, ``face``: (n, 2) their face index in
    that mesh."""
    ends: np.ndarray
    mesh: np.ndarray
    face: np.ndarray

    def __len__(self):
        return len(self.ends)


def grid_cell_size(lo, hi) -> float:
    """Edge h of the broad phase's cubic cells: the median box extent, at least 1/256 of the
    extent of all boxes."""
    extent = float((hi.max(0) - lo.min(0)).max()) or 1.0
    return max(float(np.median((hi - lo).max(1))), extent / 256, 1e-12)


def cell_entries(lo, hi, h):
    """(box, cell key) for every grid cell of size h that box [lo, hi] touches."""
    first = np.floor(lo / h).astype(np.int64)
    span = np.floor(hi / h).astype(np.int64) - first + 1
    count = np.prod(span, axis=1)
    box = np.repeat(np.arange(len(lo)), count)
    local = np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count)
    sx, sy = span[box, 0], span[box, 1]
    cell = first[box] + np.stack([local % sx, (local // sx) % sy, local // (sx * sy)], 1)
    cell -= cell.min(0)
    dims = cell.max(0) + 1
    return box, (cell[:, 0] * dims[1] + cell[:, 1]) * dims[2] + cell[:, 2]


def grid_pairs(lo, hi, h):
    """Candidate pairs (i, j), i < j, of boxes that share a grid cell of size h (unsorted, with
    repeats)."""
    box, key = cell_entries(lo, hi, h)
    order = np.lexsort((box, key))
    box, key = box[order], key[order]
    out_i, out_j = [np.zeros(0, np.int64)], [np.zeros(0, np.int64)]
    for d in range(1, len(key)):
        same = key[d:] == key[:-d]
        if not same.any():
            break
        out_i.append(box[:-d][same])
        out_j.append(box[d:][same])
    return np.concatenate(out_i), np.concatenate(out_j)   # i < j: boxes are sorted within a cell


def dense_pairs(rows, lo, hi):
    """Pairs (i, j) with i in ``rows`` and any j ≠ i whose boxes overlap (unsorted)."""
    out_i, out_j = [np.zeros(0, np.int64)], [np.zeros(0, np.int64)]
    for s in range(0, len(rows), CHUNK):
        r = rows[s:s + CHUNK]
        hit = np.all((lo[r, None, :] <= hi[None]) & (lo[None] <= hi[r, None, :]), axis=-1)
        i, j = np.nonzero(hit)
        out_i.append(r[i])
        out_j.append(j)
    i, j = np.concatenate(out_i), np.concatenate(out_j)
    keep = i != j
    return i[keep], j[keep]


def sorted_unique(a) -> np.ndarray:
    """The distinct values of the 1-D array ``a`` in ascending order (``np.unique(a)``): sorted,
    then each value kept where it differs from its predecessor (faster than ``np.unique`` on the
    broad phase's pair keys: docs/benchmarks/iteration_time.md)."""
    a = np.sort(a)
    return a[np.r_[True, a[1:] != a[:-1]]] if len(a) else a


def overlapping_pairs(lo, hi):
    """Index pairs (i, j), i < j, of the axis-aligned boxes [lo_k, hi_k] that overlap, in
    lexicographic order.

    Broad phase on a uniform grid (cell size h, :func:`grid_cell_size`): two overlapping boxes
    share at least one cell, so only boxes listed in a common cell are compared; boxes longer
    than ``LARGE_BOX_CELLS``·h (a floor's two triangles) are compared with every box directly.
    Cost O(n · boxes per cell + large boxes · n), against O(n²) for all pairs."""
    n = len(lo)
    if n < 2:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    h = grid_cell_size(lo, hi)
    large = (hi - lo).max(1) > LARGE_BOX_CELLS * h
    small = np.flatnonzero(~large)
    gi, gj = grid_pairs(lo[small], hi[small], h)
    di, dj = dense_pairs(np.flatnonzero(large), lo, hi)
    i = np.concatenate([small[gi], np.minimum(di, dj)])
    j = np.concatenate([small[gj], np.maximum(di, dj)])
    pair = sorted_unique(i * np.int64(n) + j)
    i, j = pair // n, pair % n
    hit = np.all((lo[i] <= hi[j]) & (lo[j] <= hi[i]), axis=1)
    return i[hit], j[hit]


def plane_side(V, tri_vertices, plane_tri):
    """Signed distances (·|n|) of the three vertices of each triangle to the plane of another."""
    c, d, e = (V[plane_tri[:, k]] for k in range(3))
    n = np.cross(d - c, e - c)
    return np.einsum("nkj,nj->nk", V[tri_vertices] - c[:, None, :], n)


def crossing_edges(s):
    """For signed distances s (n, 3) of a triangle's vertices that change sign: the two edges
    (k, k+1 mod 3) whose end points lie on different sides (zero counts as positive)."""
    pos = s >= 0
    edges = [(0, 1), (1, 2), (2, 0)]
    cross = np.stack([pos[:, a] != pos[:, b] for a, b in edges], 1)
    return cross


def segment_ends(V, Fa, Fb):
    """End-point candidates of the intersections of triangles Fa[i] and Fb[i] (vertex ids).

    Returns (mask of real intersections, ends (n, 2, 5) ids, lengths)."""
    sa = plane_side(V, Fa, Fb)
    sb = plane_side(V, Fb, Fa)
    straddle = lambda s: (s >= 0).any(1) & (s < 0).any(1)  # noqa: E731
    ok = straddle(sa) & straddle(sb)
    n = len(Fa)
    # four candidate points: the two crossing edges of A (on B's plane) and of B (on A's plane)
    cand_ids = np.zeros((n, 4, 5), np.int64)
    cand_p = np.zeros((n, 4, 3))
    for slot, (F, G, s) in enumerate(((Fa, Fb, sa), (Fb, Fa, sb))):
        cross = crossing_edges(s)
        k = np.argsort(~cross, axis=1, kind="stable")[:, :2]  # the (first) two crossing edges
        for m in range(2):
            a = np.take_along_axis(F, k[:, m:m + 1], 1)[:, 0]
            b = np.take_along_axis(F, ((k[:, m] + 1) % 3)[:, None], 1)[:, 0]
            sa_ = np.take_along_axis(s, k[:, m:m + 1], 1)[:, 0]
            sb_ = np.take_along_axis(s, ((k[:, m] + 1) % 3)[:, None], 1)[:, 0]
            denom = np.where(sa_ != sb_, sa_ - sb_, 1.0)
            t = sa_ / denom
            cand_p[:, 2 * slot + m] = V[a] + t[:, None] * (V[b] - V[a])
            cand_ids[:, 2 * slot + m] = np.stack([a, b, G[:, 0], G[:, 1], G[:, 2]], 1)
    # parametrise the four points along the common line and keep the overlap of the two intervals
    direction = cand_p[:, 1] - cand_p[:, 0]
    alt = cand_p[:, 3] - cand_p[:, 2]
    direction = np.where(np.linalg.norm(direction, axis=1, keepdims=True) > np.linalg.norm(alt, axis=1, keepdims=True),
                         direction, alt)
    u = np.einsum("nkj,nj->nk", cand_p - cand_p[:, :1], direction)
    lo_a, hi_a = np.sort(u[:, :2], 1).T
    lo_b, hi_b = np.sort(u[:, 2:], 1).T
    start_is_a = lo_a >= lo_b
    end_is_a = hi_a <= hi_b
    i_start = np.where(start_is_a, np.argmin(u[:, :2], 1), 2 + np.argmin(u[:, 2:], 1))
    i_end = np.where(end_is_a, np.argmax(u[:, :2], 1), 2 + np.argmax(u[:, 2:], 1))
    r = np.arange(n)
    p0, p1 = cand_p[r, i_start], cand_p[r, i_end]
    ok &= np.maximum(lo_a, lo_b) < np.minimum(hi_a, hi_b)
    ends = np.stack([cand_ids[r, i_start], cand_ids[r, i_end]], 1)
    return ok, ends, np.linalg.norm(p1 - p0, axis=1)


def intersection_segments(vertices: list, faces: list, rel_min_length: float = 1e-7) -> Segments:
    """Intersection segments among the meshes (V_k, F_k) and within each of them.

    Triangles of one mesh that share a welded vertex are neighbours and never tested."""
    offsets = np.cumsum([0] + [len(V) for V in vertices])
    V = np.concatenate([np.asarray(v, float) for v in vertices]) if vertices else np.zeros((0, 3))
    if len(V) == 0:
        return Segments(np.zeros((0, 2, 5), np.int64), np.zeros((0, 2), np.int64), np.zeros((0, 2), np.int64))
    wid, _ = weld(V)
    extent = float(np.ptp(V, axis=0).max()) or 1.0
    Fs = [np.asarray(F, np.int64) + o for F, o in zip(faces, offsets)]
    sizes = [len(F) for F in Fs]
    start = np.cumsum([0] + sizes)
    F_all = np.concatenate(Fs)
    part = np.repeat(np.arange(len(Fs)), sizes)
    gi, gj = overlapping_pairs(V[F_all].min(1) - 1e-9 * extent, V[F_all].max(1) + 1e-9 * extent)
    ends, mesh, face = [], [], []
    for a in range(len(Fs)):
        for b in range(a, len(Fs)):
            sel = (part[gi] == a) & (part[gj] == b)
            if a != b:  # the pairs with one triangle in each mesh, either way round
                sel |= (part[gi] == b) & (part[gj] == a)
            i, j = gi[sel], gj[sel]
            i, j = np.where(part[i] == a, i, j) - start[a], np.where(part[i] == a, j, i) - start[b]
            if a == b and len(i):  # neighbours share a welded vertex
                wa, wb = wid[Fs[a][i]], wid[Fs[b][j]]
                shared = (wa[:, :, None] == wb[:, None, :]).any((1, 2))
                i, j = i[~shared], j[~shared]
            if not len(i):
                continue
            order = np.lexsort((j, i))  # row-major, as a dense (i, j) test lists them
            i, j = i[order], j[order]
            ok, e, length = segment_ends(V, Fs[a][i], Fs[b][j])
            ok &= length > rel_min_length * extent
            ends.append(e[ok])
            mesh.append(np.tile([a, b], (int(ok.sum()), 1)))
            face.append(np.stack([i[ok], j[ok]], 1))
    if not ends:
        return Segments(np.zeros((0, 2, 5), np.int64), np.zeros((0, 2), np.int64), np.zeros((0, 2), np.int64))
    return Segments(np.concatenate(ends), np.concatenate(mesh), np.concatenate(face))


def plane_crossing(P, ids):
    """p = a + t (b − a) with t = ((c − a)·n)/((b − a)·n), n = (d − c) × (e − c), differentiable
    in the flat vertex buffer ``P``; ``ids`` are the five vertex-id arrays (a, b, c, d, e)."""
    a, b, c, d, e = (dr.gather(mi.Point3f, P, jit_array(mi.UInt32, i)) for i in ids)
    n = dr.cross(d - c, e - c)
    denom = dr.dot(b - a, n)
    t = dr.dot(c - a, n) / dr.select(denom != 0, denom, 1.0)
    return a + t * (b - a)


def segment_points(P, segments: Segments):
    """(p0, p1) of every segment as AD points of the flat vertex buffer ``P``."""
    return tuple(plane_crossing(P, [segments.ends[:, k, m] for m in range(5)]) for k in range(2))
