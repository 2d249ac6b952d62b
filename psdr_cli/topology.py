"""Mesh topology for boundary sampling: welded vertices, edges with their faces, edge classes.

Built once per mesh change, in numpy. Vertex ids refer to the mesh as Mitsuba holds it, so the
estimators gather edge end points from the differentiable ``vertex_positions`` buffer every
iteration and the edges move with the parameters.

For an edge (v0, v1) shared by faces f0 and f1, v0 → v1 follows f0's winding and v2 is f0's third
vertex, so n0 = normalize((p1 − p0) × (p2 − p0)). The edge is

- *open* when only f0 exists (a mesh border),
- *flat* when n0·n1 > 1 − ε (never a silhouette),
- *concave* when f0's third vertex lies in front of f1's plane: (p2 − p0)·n1 > ε|p2 − p0|.
  A ray grazing a concave edge of an opaque solid enters it, so such edges only matter for
  transmissive materials.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .meshes import weld


def face_normals(V, F):
    """Unit normals (p1 − p0) × (p2 − p0) / |·| of triangles F."""
    n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)


@dataclass
class Topology:
    """Edges of a triangle mesh; every array has one row per edge.

    ``v0, v1, v2``: vertex ids (v2 = third vertex of face0); ``face0, face1``: adjacent faces
    (face1 = −1 on open edges); ``open``, ``flat``, ``concave``: edge classes; ``nonmanifold``:
    number of edges with more than two faces (only the first two are kept).
    """
    v0: np.ndarray
    v1: np.ndarray
    v2: np.ndarray
    face0: np.ndarray
    face1: np.ndarray
    open: np.ndarray
    flat: np.ndarray
    concave: np.ndarray
    nonmanifold: int
    faces: np.ndarray

    def __len__(self):
        return len(self.v0)

    def secondary(self, transmissive: bool = False) -> np.ndarray:
        """Indices of edges that can bound visibility of a boundary segment."""
        keep = ~self.flat & (transmissive | ~self.concave)
        return np.nonzero(keep)[0]

    def facing(self, V, camera_origin):
        """Whether face0 and face1 (face0 again on open edges) face ``camera_origin``."""
        V = np.asarray(V, float)
        n = face_normals(V, self.faces)
        to_cam = np.asarray(camera_origin, float) - V[self.v0]
        s0 = np.einsum("ij,ij->i", n[self.face0], to_cam) > 0
        f1 = np.where(self.open, self.face0, self.face1)
        return s0, np.einsum("ij,ij->i", n[f1], to_cam) > 0

    def primary(self, V, camera_origin) -> np.ndarray:
        """Indices of silhouette edges seen from ``camera_origin``: open edges, and edges where
        exactly one adjacent face faces the camera."""
        s0, s1 = self.facing(V, camera_origin)
        return np.nonzero(self.open | (s0 != s1))[0]

    def creases(self, V, camera_origin) -> np.ndarray:
        """Indices of the edges of a flat-shaded mesh that can show as image discontinuities from
        ``camera_origin``: open edges and non-flat edges with at least one face towards it."""
        s0, s1 = self.facing(V, camera_origin)
        return np.nonzero(self.open | (~self.flat & (s0 | s1)))[0]


def build_topology(V, F, eps: float = 1e-5) -> Topology:
    """Edge table of the mesh (V, F), vertices welded by position (vertex ids stay V's)."""
    V = np.asarray(V, float)
    F = np.asarray(F, np.int64)
    wid, _ = weld(V)
    Fw = wid[F]
    # Half-edges k of face f: (F[f,k], F[f,k+1]); grouped by their welded, unordered end points.
    a = Fw.reshape(-1)
    b = Fw[:, [1, 2, 0]].reshape(-1)
    key = np.minimum(a, b) * (wid.max() + 1) + np.maximum(a, b)
    order = np.argsort(key, kind="stable")
    key_sorted = key[order]
    starts = np.nonzero(np.r_[True, key_sorted[1:] != key_sorted[:-1]])[0]
    counts = np.diff(np.r_[starts, len(key_sorted)])
    first = order[starts]
    second = np.where(counts > 1, order[np.minimum(starts + 1, len(order) - 1)], -1)
    f0, k0 = first // 3, first % 3
    v0 = F[f0, k0]
    v1 = F[f0, (k0 + 1) % 3]
    v2 = F[f0, (k0 + 2) % 3]
    open_ = second < 0
    f1 = np.where(open_, -1, second // 3)
    n = face_normals(V, F)
    n0 = n[f0]
    n1 = n[np.where(open_, f0, f1)]
    flat = ~open_ & (np.einsum("ij,ij->i", n0, n1) > 1 - eps)
    d = V[v2] - V[v0]
    concave = ~open_ & ~flat & (np.einsum("ij,ij->i", d, n1) > eps * np.linalg.norm(d, axis=1))
    return Topology(v0=v0, v1=v1, v2=v2, face0=f0, face1=f1, open=open_, flat=flat, concave=concave,
                    nonmanifold=int((counts > 2).sum()), faces=F)
