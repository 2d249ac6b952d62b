"""Remeshing of the optimised shape: field-aligned (Instant Meshes) or isotropic (MeshLab).

Field-aligned remeshing (Jakob et al. 2015, ``pyinstantmeshes``) gives regular, mostly
edge-aligned triangulations, which edge sorting turns into long chains (paper §4.3). The mesh is
normalised to a unit box before remeshing (Instant Meshes' parameters assume it) and mapped back
afterwards. Instant Meshes leaves small holes now and then; they are closed with MeshLab, and if
the result is still not closed the isotropic remesher (``pymeshlab``) is used instead.
"""
from __future__ import annotations

import contextlib
import os
import sys

import numpy as np
import pyinstantmeshes
import pymeshlab

from .meshes import face_areas
from .topology import build_topology


@contextlib.contextmanager
def quiet():
    """Silence C/C++ output on stdout/stderr (file-descriptor level), e.g. Instant Meshes' log,
    so it cannot break the progress display."""
    sys.stdout.flush()
    sys.stderr.flush()
    saved = os.dup(1), os.dup(2)
    with open(os.devnull, "w") as null:
        os.dup2(null.fileno(), 1)
        os.dup2(null.fileno(), 2)
        try:
            yield
        finally:
            os.dup2(saved[0], 1)
            os.dup2(saved[1], 2)
            os.close(saved[0])
            os.close(saved[1])


def normalise(V):
    """(V', centre, scale) with V' = (V − centre)/scale inside the unit box."""
    lo, hi = V.min(0), V.max(0)
    centre, scale = (lo + hi) / 2, float((hi - lo).max()) or 1.0
    return (V - centre) / scale, centre, scale


def open_edges(V, F) -> int:
    t = build_topology(V, F)
    return int(t.open.sum()) + t.nonmanifold


def _meshlab(V, F):
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(np.asarray(V, np.float64), np.asarray(F, np.int32)))
    return ms


def _closed(ms):
    """Merge duplicates, drop non-manifold bits, close holes, orient faces coherently."""
    ms.meshing_remove_duplicate_vertices()
    ms.meshing_remove_unreferenced_vertices()
    ms.meshing_repair_non_manifold_edges()
    ms.meshing_close_holes(maxholesize=60)
    ms.meshing_re_orient_faces_coherently()
    m = ms.current_mesh()
    return np.asarray(m.vertex_matrix(), float), np.asarray(m.face_matrix(), np.int64)


def instant_meshes(V, F, vertices: int):
    """Field-aligned triangle mesh with about ``vertices`` vertices."""
    Vn, centre, scale = normalise(np.asarray(V, float))
    with quiet():
        V2, F2 = pyinstantmeshes.remesh(Vn.astype(np.float32), np.asarray(F, np.int32), int(vertices),
                                        deterministic=True)
        V2, F2 = _closed(_meshlab(V2, F2))
    return V2 * scale + centre, F2


def isotropic(V, F, vertices: int, iterations: int = 6):
    """Isotropic remeshing (MeshLab) with the edge length that gives about ``vertices`` vertices
    on the current surface area (a closed triangle mesh has A ≈ (√3/4)·ℓ²·2·n)."""
    Vn, centre, scale = normalise(np.asarray(V, float))
    area = float(face_areas(Vn, np.asarray(F)).sum())
    length = float(np.sqrt(area / (vertices * np.sqrt(3) / 2)))
    ms = _meshlab(Vn, F)
    with quiet():
        ms.meshing_isotropic_explicit_remeshing(iterations=iterations, targetlen=pymeshlab.PureValue(length))
        V2, F2 = _closed(ms)
    return V2 * scale + centre, F2


def outward(V, F):
    """Faces flipped if needed so that the enclosed (signed) volume is positive."""
    a, b, c = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    volume = np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6
    return F if volume >= 0 else F[:, ::-1].copy()


def remesh(V, F, vertices: int, method: str = "instant"):
    """Remesh (V, F) to about ``vertices`` vertices; returns a closed, outward-oriented mesh
    (falls back to the isotropic method when the field-aligned one leaves holes)."""
    if method == "instant":
        V2, F2 = instant_meshes(V, F, vertices)
        if len(F2) > 0 and open_edges(V2, F2) == 0:
            return V2, outward(V2, F2)
    V2, F2 = isotropic(V, F, vertices)
    return V2, outward(V2, F2)
