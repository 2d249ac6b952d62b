"""Mesh topology for boundary sampling: welded vertices, edges with their faces, edge classes.

Built once per mesh change, in numpy. Vertex ids refer to the mesh as Mitsuba holds it, so the
estimators gather edge end points from the differentiable ``vertex_positions`` buffer every
iteration and the edges move with the parameters.

For an edge (v0, v1) shared by faces f0 and f1, v0 → v1 follows f0's winding, v2 is f0's third
vertex and v3 f1's, so n0 = normalize((p1 − p0) × (p2 − p0)) and n1 = normalize((p0 − p1) ×
(p3 − p1)): f1's normal when f1 traverses the edge as (v1, v0), as in a consistently oriented
mesh, and its flipped normal otherwise. The edge is

- *open* when only f0 exists (a mesh border),
- *flat* when n0·n1 > 1 − ε (never a silhouette),
- *concave* when f0's third vertex lies in front of f1's plane: (p2 − p0)·n1 > ε|p2 − p0|.
  A ray grazing a concave edge of an opaque solid enters it, so such edges only matter for
  transmissive materials.

An edge with k > 2 faces (non-manifold: a fin, pages on a spine, two boxes sharing an edge) has
one row per sector between angular neighbours, each row a two-face edge whose normals point into
its sector; the sector wider than π (at most one) is the only one with silhouettes.
"""
from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np
from scipy import sparse
from scipy.sparse import csgraph

from ..scene.meshes import weld


def face_normals(V, F):
    """Unit normals (p1 − p0) × (p2 − p0) / |·| of triangles F."""
    n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)


def unit(v):
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-30)


@dataclass
class Topology:
    """Edges of a triangle mesh; every array has one row per edge (one row per sector of an edge
    with more than two faces).

    ``v0, v1, v2``: face0's vertices, v2 its third; ``v3``: face1's third vertex (v2 on open
    edges). The row's normals are n0 = (p1 − p0) × (p2 − p0) and n1 = (p0 − p1) × (p3 − p1): on an
    edge with two faces v0 → v1 follows face0's winding, and n1 is face1's normal when the two
    faces are oriented alike, or face1's flipped normal when not (a mesh with some faces turned
    over), so the edge classes and silhouettes never depend on face orientation. ``face0,
    face1``: adjacent faces (face1 = −1 on open edges); ``open``, ``flat``, ``concave``: edge
    classes; ``sector``: rows of an edge with more than two faces; ``turned0``, ``turned1``:
    whether face0's (face1's) winding normal is −n0 (−n1), i.e. its back is towards the row's
    sector (a one-sided material shades the back black, so two coplanar faces of which one is
    turned meet in an image discontinuity); ``nonmanifold``: the number of edges with more than two faces.
    """
    v0: np.ndarray
    v1: np.ndarray
    v2: np.ndarray
    v3: np.ndarray
    face0: np.ndarray
    face1: np.ndarray
    open: np.ndarray
    flat: np.ndarray
    concave: np.ndarray
    sector: np.ndarray
    turned0: np.ndarray
    turned1: np.ndarray
    nonmanifold: int
    faces: np.ndarray

    def __len__(self):
        return len(self.v0)

    def secondary(self, transmissive: bool = False) -> np.ndarray:
        """Indices of edges that can bound visibility of a boundary segment."""
        keep = ~self.flat & (transmissive | ~self.concave)
        return np.nonzero(keep)[0]

    def normals(self, V):
        """(n0, n1) per row (:func:`row_normals`)."""
        return row_normals(np.asarray(V, float), (self.v0, self.v1, self.v2, self.v3), self.open)

    def facing(self, V, camera_origin, normals=None):
        """Whether n0 and n1 point towards ``camera_origin`` (``normals``: :meth:`normals` of V if
        already computed)."""
        n0, n1 = self.normals(V) if normals is None else normals
        to_cam = np.asarray(camera_origin, float) - np.asarray(V, float)[self.v0]
        return np.einsum("ij,ij->i", n0, to_cam) > 0, np.einsum("ij,ij->i", n1, to_cam) > 0

    def primary(self, V, camera_origin, normals=None) -> np.ndarray:
        """Indices of silhouette edges seen from ``camera_origin``: open edges, and edges where
        exactly one of n0, n1 faces the camera (on a sector row, only the sector wider than π:
        a narrower one never holds a line through the edge)."""
        s0, s1 = self.facing(V, camera_origin, normals)
        return np.nonzero(self.open | ((s0 != s1) & ~(self.sector & self.concave)))[0]

    def creases(self, V, camera_origin, normals=None) -> np.ndarray:
        """Indices of the edges of a flat-shaded mesh that can show as image discontinuities from
        ``camera_origin``: open edges, and non-flat edges or edges between a turned and an
        unturned face, of which at least one face shows its front (by its winding) to the camera:
        the back of a one-sided material is black, and an edge between two back faces of a
        closed mesh is never seen (near a silhouette it projects just behind a grazing front
        face). On a sector row the camera must also lie inside the sector: in front of both of
        n0, n1 when the sector is narrower than π, of either otherwise."""
        s0, s1 = self.facing(V, camera_origin, normals)
        front = (s0 != self.turned0) | (s1 != self.turned1)
        inside = np.where(self.concave, s0 & s1, s0 | s1)
        seen = front & (~self.sector | inside)
        jump = ~self.flat | (self.turned0 != self.turned1)
        return np.nonzero(self.open | (jump & seen))[0]


def sector_pairs(V, F, wid, halfedges):
    """Rows (h_a, h_b, forward_a, β) of an edge shared by the half-edges ``halfedges`` (face·3 + k):
    the faces sorted by their angle about the edge, one row per pair of neighbours, face a
    followed by face b counter-clockwise about e = the first half-edge's direction, β the
    sector's angle from a to b, and ``forward_a`` whether face a traverses the edge along e.

    With p the edge's first end point and t_i the unit component of face i's third vertex − p
    normal to e, the angle of face i is atan2(t_i · (e × t_0), t_i · t_0)."""
    f, k = halfedges // 3, halfedges % 3
    a = F[f, k]
    p, q = V[a[0]], V[F[f[0], (k[0] + 1) % 3]]
    e = unit(q - p)
    t = V[F[f, (k + 2) % 3]] - p
    t = unit(t - np.outer(t @ e, e))
    w = np.cross(e, t[0])
    angle = np.mod(np.arctan2(t @ w, t @ t[0]), 2 * np.pi)
    order = np.argsort(angle, kind="stable")
    forward = wid[a] == wid[a[0]]
    beta = np.mod(angle[np.roll(order, -1)] - angle[order], 2 * np.pi)
    beta[-1] = 2 * np.pi - beta[:-1].sum()
    return [(halfedges[i], halfedges[j], forward[i], b) for i, j, b in zip(order, np.roll(order, -1), beta)]


def edge_groups(F):
    """Half-edges h = 3f + k of face f, (F[f,k], F[f,k+1]), grouped by their unordered end points:
    (key per half-edge, half-edges sorted by key, start of each group in that order, its size)."""
    a, b = F.reshape(-1), F[:, [1, 2, 0]].reshape(-1)
    key = np.minimum(a, b) * (F.max() + 1) + np.maximum(a, b)
    order = np.argsort(key, kind="stable")
    ks = key[order]
    starts = np.nonzero(np.r_[True, ks[1:] != ks[:-1]])[0]
    return key, order, starts, np.diff(np.r_[starts, len(ks)])


def face_graph(F):
    """(f, g, same): pairs of faces sharing an edge with no third face, and whether f and g
    traverse it in the same direction (their windings disagree)."""
    _, order, starts, counts = edge_groups(F)
    h, g = order[starts[counts == 2]], order[starts[counts == 2] + 1]
    a = F.reshape(-1)
    return h // 3, g // 3, a[h] == a[g]


def closed_parts(F, label):
    """Per part: whether each of its edges has exactly two of its faces. An edge with two faces
    joins them into one part, so only edges with one face or more than two are counted."""
    key, order, starts, counts = edge_groups(F)
    other = order[np.repeat(counts != 2, counts)]
    part = label[other // 3]
    _, pair, pair_counts = np.unique(np.stack([key[other], part], 1), axis=0, return_inverse=True,
                                     return_counts=True)
    bad = np.bincount(part, weights=pair_counts[pair.reshape(-1)] != 2, minlength=label.max() + 1)
    return bad == 0


def winding_numbers(V, F, points) -> np.ndarray:
    """(points, faces) signed solid angles / 4π of the triangles F seen from each point (Van
    Oosterom and Strackee: tan(Ω/2) = det(a, b, c) / (|a||b||c| + (a·b)|c| + (a·c)|b| + (b·c)|a|),
    a, b, c the corners relative to the point). Summed over a closed, outward surface: 1 inside,
    0 outside."""
    out = []
    for p in np.asarray(points, float).reshape(-1, 3):
        a, b, c = (V[F[:, k]] - p for k in range(3))
        la, lb, lc = (np.linalg.norm(x, axis=1) for x in (a, b, c))
        det = np.einsum("ij,ij->i", a, np.cross(b, c))
        den = la * lb * lc + np.einsum("ij,ij->i", a, b) * lc + np.einsum("ij,ij->i", a, c) * lb \
            + np.einsum("ij,ij->i", b, c) * la
        out.append(np.arctan2(det, den) / (2 * np.pi))
    return np.array(out).reshape(-1, len(F))


def boxed_points(corners, points) -> np.ndarray:
    """The ``points`` (n, 3) inside the axis-aligned bounding box of ``corners`` (boundary
    included): outside it a closed surface through those corners has winding number 0, so only
    these can be enclosed (:func:`oriented_parts` computes no winding numbers for the others)."""
    points = np.asarray(points, float).reshape(-1, 3)
    if not len(corners):
        return points[:0]
    lo, hi = corners.min(0), corners.max(0)
    return points[np.all((points >= lo) & (points <= hi), axis=1)]


@dataclass(frozen=True)
class FaceParts:
    """What :func:`oriented_parts` needs of a welded face array F alone: per face its part
    (``label``) and whether its winding must be reversed to agree with its part's root face
    (``parity``), whether its part is closed and orientable (``solid``); and the half-edge groups
    of F (:func:`edge_groups`)."""
    label: np.ndarray
    parity: np.ndarray
    solid: np.ndarray
    groups: tuple


def face_parts(F) -> FaceParts:
    """:class:`FaceParts` of the welded faces F: parity(f) = parity(parent) XOR same(parent, f)
    over breadth-first trees of the parts (scipy.sparse.csgraph), accumulated to the roots by
    pointer doubling; a part is solid when every edge has two of its faces and no face pair
    still traverses a shared edge in the same direction."""
    n = len(F)
    f, g, same = face_graph(F)
    # 1 for opposite traversals, 4 for the same; two faces sharing two edges add up (2, 5 or 8)
    link = sparse.coo_matrix((np.where(same, 4.0, 1.0), (f, g)), shape=(n, n)).tocsr()
    _, label = csgraph.connected_components(link, directed=False)
    # one breadth-first tree over all parts: a root node n joined to one face of each part
    roots = np.unique(label, return_index=True)[1]
    tree = sparse.coo_matrix((np.r_[np.where(same, 4.0, 1.0), np.ones(len(roots))],
                              (np.r_[f, np.full(len(roots), n)], np.r_[g, roots])), shape=(n + 1, n + 1)).tocsr()
    tree = tree + tree.T
    order, pred = csgraph.breadth_first_order(tree, n, directed=False)
    child = order[1:]
    parent = np.r_[pred[:n], n]
    parity = np.zeros(n + 1, bool)
    parity[child] = np.asarray(tree[child, pred[child]]).ravel() % 4 == 0
    while (parent != parent[parent]).any():
        parity ^= parity[parent]
        parent = parent[parent]
    parity = parity[:n]
    twisted = same ^ parity[f] ^ parity[g]  # still the same direction: a non-orientable part
    solid = (closed_parts(F, label) & (np.bincount(label[f], weights=twisted, minlength=label.max() + 1) == 0))[label]
    return FaceParts(label, parity, solid, edge_groups(F))


#: :class:`FaceParts` of the face arrays used last (by content, least recently used first): an
#: optimisation rebuilds the edge table every iteration from new vertices, but the faces change
#: only at a remesh. The edge table is built on the loop's worker thread and on the main thread.
_FACE_PARTS: dict = {}
_FACE_PARTS_KEPT = 16
_FACE_PARTS_LOCK = threading.Lock()


def cached_face_parts(F) -> FaceParts:
    """:func:`face_parts` of F, computed once per distinct face array (its dtype, shape and bytes
    as the key; the arrays are read-only results, shared by every caller)."""
    key = (F.dtype.str, F.shape, F.tobytes())
    with _FACE_PARTS_LOCK:
        parts = _FACE_PARTS.pop(key, None)
        if parts is not None:
            _FACE_PARTS[key] = parts   # now the most recently used
            return parts
    parts = face_parts(F)
    for a in (parts.label, parts.parity, parts.solid, *parts.groups):
        a.setflags(write=False)
    with _FACE_PARTS_LOCK:
        _FACE_PARTS[key] = parts
        while len(_FACE_PARTS) > _FACE_PARTS_KEPT:
            _FACE_PARTS.pop(next(iter(_FACE_PARTS)))
    return parts


def oriented_parts(V, F, parts: FaceParts, viewpoints=()):
    """(flipped, solid) per face of a welded mesh (V, F): whether its winding must be reversed so
    that every connected part (faces joined through edges with two faces) is consistently
    oriented, towards free space where the part is closed; and whether the part is closed and
    orientable, so that paths stay on one side of it.

    A closed part's free space is its outside (signed volume Σ det(p0, p1, p2)/6 > 0), unless it
    encloses one of the ``viewpoints`` (camera origins; winding number ≥ ½): a room seen from
    inside (only viewpoints inside the solid faces' bounding box are tested: :func:`boxed_points`).
    ``parts``: F's :class:`FaceParts`, which depend on F alone (:func:`cached_face_parts`)."""
    label, parity, solid = parts.label, parts.parity, parts.solid
    G = np.where(parity[:, None], F[:, ::-1], F)
    det = np.einsum("ij,ij->i", V[G[:, 0]], np.cross(V[G[:, 1]], V[G[:, 2]]))
    inward = np.bincount(label, weights=det) < 0
    room = np.zeros(len(inward), bool)
    inside = boxed_points(V[G[solid]].reshape(-1, 3), viewpoints)
    if len(inside):
        w = winding_numbers(V, G[solid], inside)
        enclosed = np.abs(np.stack([np.bincount(label[solid], weights=x, minlength=len(room)) for x in w])) >= 0.5
        room = enclosed.any(0)
    return parity ^ (solid & (inward != room)[label]), solid


def row_normals(V, ids, open_):
    """(n0, n1) of edge rows (v0, v1, v2, v3): unit (p1 − p0) × (p2 − p0) and (p0 − p1) × (p3 − p1)
    (n0 on open edges)."""
    v0, v1, v2, v3 = ids
    n0 = unit(np.cross(V[v1] - V[v0], V[v2] - V[v0]))
    return n0, np.where(open_[:, None], n0, unit(np.cross(V[v0] - V[v1], V[v3] - V[v1])))


def row_geometry(V, F, wid, h0, h1, forward):
    """Vertex ids (v0, v1, v2, v3) and normals (n0, n1) of edge rows: face0 = h0 // 3 traversed
    along its winding (``forward``) or against it, face1 = h1 // 3 (−1: open), n1 consistent with
    n0; and whether face1's winding normal is −n1."""
    f0, k0 = h0 // 3, h0 % 3
    first, second = F[f0, k0], F[f0, (k0 + 1) % 3]
    v0, v1, v2 = np.where(forward, first, second), np.where(forward, second, first), F[f0, (k0 + 2) % 3]
    open_ = h1 < 0
    f1, k1 = np.maximum(h1, 0) // 3, np.maximum(h1, 0) % 3
    v3 = np.where(open_, v2, F[f1, (k1 + 2) % 3])
    # face1's winding normal is n1 exactly when it traverses the edge as (v1, v0)
    turned1 = ~open_ & (wid[F[f1, k1]] != wid[v1])
    return (v0, v1, v2, v3), row_normals(V, (v0, v1, v2, v3), open_), turned1


def edge_classes(V, ids, normals, open_, eps):
    """(flat, concave) of edge rows: n0·n1 > 1 − ε, and (p2 − p0)·n1 > ε|p2 − p0|."""
    v0, _, v2, _ = ids
    n0, n1 = normals
    flat = ~open_ & (np.einsum("ij,ij->i", n0, n1) > 1 - eps)
    d = V[v2] - V[v0]
    concave = ~open_ & ~flat & (np.einsum("ij,ij->i", d, n1) > eps * np.linalg.norm(d, axis=1))
    return flat, concave


def build_topology(V, F, eps: float = 1e-5, viewpoints=()) -> Topology:
    """Edge table of the mesh (V, F), vertices welded by position (vertex ids stay V's).

    An edge with two faces gets one row, its normals those of the consistently oriented part
    (:func:`oriented_parts`): towards free space on a closed part (outward, or inward for a part
    enclosing one of the ``viewpoints``), so that its concave edges can be left out for opaque
    materials; on an open part turned into the sector wider than π, since both sides
    of an open surface are free space. An edge with more than two faces gets one row per sector
    between neighbouring faces (:func:`sector_pairs`), its normals turned into the sector: a line
    through the edge is a visibility boundary only inside a sector wider than π (all faces on
    one side of it), and the camera sees the crease between the two faces of the sector it lies
    in. Rendering keeps each face's own winding (``turned0``, ``turned1``)."""
    V = np.asarray(V, float)
    F = np.asarray(F, np.int64)
    wid, rep = weld(V)
    Fw = wid[F]
    parts = cached_face_parts(Fw)
    flipped, solid = oriented_parts(V[rep], Fw, parts, viewpoints)
    _, order, starts, counts = parts.groups  # by welded end points
    simple = counts <= 2
    h0 = order[starts[simple]]
    h1 = np.where(counts[simple] == 2, order[np.minimum(starts[simple] + 1, len(order) - 1)], -1)
    forward, beta = ~flipped[h0 // 3], np.full(len(h0), np.nan)
    ids, normals, _ = row_geometry(V, F, wid, h0, h1, forward)
    _, concave = edge_classes(V, ids, normals, h1 < 0, eps)
    forward ^= concave & ~solid[h0 // 3]  # open part: the sector wider than π
    rows = [sector_pairs(V, F, wid, order[s: s + c]) for s, c in zip(starts[~simple], counts[~simple])]
    rows = [r for edge in rows for r in edge]
    if rows:
        ha, hb, fw, angle = (np.array(c) for c in zip(*rows))
        h0, h1, forward, beta = np.r_[h0, ha], np.r_[h1, hb], np.r_[forward, fw], np.r_[beta, angle]
    sector = np.r_[np.zeros(int(simple.sum()), bool), np.ones(len(rows), bool)]
    open_ = h1 < 0
    ids, normals, turned1 = row_geometry(V, F, wid, h0, h1, forward)
    flat, concave = edge_classes(V, ids, normals, open_, eps)
    # sector rows: classes from the sector angle (a sector of angle 0, between two coincident faces,
    # has n1 = −n0 and would pass for a blade wider than π)
    flat = np.where(sector, np.abs(beta - np.pi) < np.sqrt(2 * eps), flat)
    concave = np.where(sector, (beta < np.pi) & ~flat, concave)
    return Topology(*ids, face0=h0 // 3, face1=np.where(open_, -1, h1 // 3), open=open_, flat=flat,
                    concave=concave, sector=sector, turned0=~forward, turned1=turned1,
                    nonmanifold=int((~simple).sum()), faces=F)
