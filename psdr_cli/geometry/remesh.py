"""Remeshing of the optimised shape: field-aligned (Instant Meshes) or isotropic (MeshLab).

Field-aligned remeshing (Jakob et al. 2015, ``pyinstantmeshes``) gives regular, mostly
edge-aligned triangulations, which edge sorting turns into long chains (paper §4.3). The mesh is
normalised to a unit box before remeshing (Instant Meshes' parameters assume it) and mapped back
afterwards. Instant Meshes leaves small holes and non-manifold bits now and then; MeshLab
repairs them. A remesh must never end an optimisation: every result is checked
(:func:`defects`: finite, closed, 2-manifold, consistently oriented, no degenerate faces), and a
method that raises or returns a defective mesh falls back to the next one,

    instant → isotropic → the input mesh unchanged,

each fallback reported through ``warn``.
"""
from __future__ import annotations

import contextlib
import os
import sys

import numpy as np
import pyinstantmeshes
import pymeshlab

from ..scene.meshes import degenerate_faces, face_areas
from .topology import build_topology

#: Fallback order after each method (the input mesh is the last resort).
FALLBACK = {"instant": ("instant", "isotropic"), "isotropic": ("isotropic",)}


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


def defects(V, F) -> list[str]:
    """What makes (V, F) unusable as an optimised surface (empty when nothing): non-finite
    vertices, too few faces, degenerate faces, open or non-manifold edges, and interior edges
    whose two faces traverse them in the same direction (inconsistent orientation)."""
    V, F = np.asarray(V, float), np.asarray(F, np.int64)
    if len(F) < 4 or len(V) < 4:
        return [f"only {len(V)} vertices and {len(F)} faces"]
    if not np.isfinite(V).all():
        return ["non-finite vertices"]
    if F.min() < 0 or F.max() >= len(V):
        return ["face indices out of range"]
    out = []
    bad = int(degenerate_faces(V, F).sum())
    if bad:
        out.append(f"{bad} degenerate faces")
    t = build_topology(V, F)
    if t.open.any():
        out.append(f"{int(t.open.sum())} open edges")
    if t.nonmanifold:
        out.append(f"{t.nonmanifold} non-manifold edges")
    # the two faces of an edge traverse it in the same direction
    same = ~t.open & ~t.sector & (t.turned0 != t.turned1)
    if same.any():
        out.append(f"{int(same.sum())} edges with inconsistent face orientation")
    return out


def _meshlab(V, F):
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(np.asarray(V, np.float64), np.asarray(F, np.int32)))
    return ms


def _closed(ms):
    """Merge duplicates, drop non-manifold bits, close holes, orient faces coherently (MeshLab
    refuses to orient a mesh that is still not 2-manifold: the repairs run twice, and the
    orientation is left to :func:`outward` and the caller's check if it still fails)."""
    ms.meshing_remove_duplicate_vertices()
    ms.meshing_remove_unreferenced_vertices()
    for _ in range(2):
        ms.meshing_repair_non_manifold_edges()
        ms.meshing_repair_non_manifold_vertices()
        ms.meshing_close_holes(maxholesize=60)
        ms.meshing_remove_unreferenced_vertices()
    try:
        ms.meshing_re_orient_faces_coherently()
    except pymeshlab.PyMeshLabException:
        pass  # still not 2-manifold: defects() reports it and remesh() falls back
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


def remesh(V, F, vertices: int, method: str = "instant", warn=None):
    """Remesh (V, F) to about ``vertices`` vertices; returns a closed, 2-manifold,
    outward-oriented mesh. Never raises for a bad intermediate result: a method that fails or
    leaves :func:`defects` falls back to the next (instant → isotropic), and when every method
    fails the input mesh is returned unchanged. ``warn(message)`` hears of each fallback."""
    methods = {"instant": instant_meshes, "isotropic": isotropic}
    for name in FALLBACK[method]:
        try:
            V2, F2 = methods[name](V, F, vertices)
            problems = defects(V2, F2)
        except Exception as exc:  # noqa: BLE001 - any failure of the external remeshers
            problems = [f"{type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}"]
        if not problems:
            return V2, outward(V2, F2)
        if warn:
            warn(f"remesh ({name}, {vertices} vertices) failed: {'; '.join(problems)}; "
                 f"{'trying the next method' if name != FALLBACK[method][-1] else 'keeping the current mesh'}")
    return np.asarray(V, float), np.asarray(F, np.int64)
