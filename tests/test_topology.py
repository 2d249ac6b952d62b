"""Edge tables: counts, classes (open, flat, concave), welding, silhouettes."""
import numpy as np

from psdr_cli import meshes
from psdr_cli.topology import build_topology, face_normals, weld


def test_cube_edges_are_convex_and_diagonals_flat():
    V, F = meshes.cube((1, 1, 1))
    t = build_topology(V, F)
    assert len(t) == 18 and t.nonmanifold == 0 and not t.open.any()
    assert t.flat.sum() == 6 and not t.concave.any()
    assert len(t.secondary()) == 12


def test_edge_orientation_follows_face0_winding():
    V, F = meshes.sphere(1.0, 1)
    t = build_topology(V, F)
    n = face_normals(V, F)
    n0 = np.cross(V[t.v1] - V[t.v0], V[t.v2] - V[t.v0])
    n0 /= np.linalg.norm(n0, axis=1, keepdims=True)
    assert np.allclose(n0, n[t.face0])
    # face1 holds the same edge in the opposite direction (consistently oriented mesh)
    for e in range(len(t)):
        f1 = list(F[t.face1[e]])
        i = f1.index(t.v1[e])
        assert f1[(i + 1) % 3] == t.v0[e]


def test_open_plane_and_torus_concavity():
    V, F = meshes.plane((2, 2))
    t = build_topology(V, F)
    assert len(t) == 5 and t.open.sum() == 4 and t.flat.sum() == 1
    V, F = meshes.torus(1.0, 0.3, 24, 12)
    t = build_topology(V, F)
    assert not t.open.any() and t.concave.any() and (~t.concave & ~t.flat).any()
    # concave edges sit on the inner half of the tube (closer to the axis than the tube centre)
    mid = (V[t.v0] + V[t.v1]) / 2
    r = np.hypot(mid[:, 0], mid[:, 1])
    assert np.mean(r[t.concave] < 1.0) > 0.9
    assert len(t.secondary(transmissive=True)) > len(t.secondary())


def test_seam_split_vertices_are_welded():
    V, F = meshes.cube((1, 1, 1))
    # split every face into its own vertices (as an OBJ with per-face UVs would)
    V2 = V[F.reshape(-1)]
    F2 = np.arange(len(V2)).reshape(-1, 3)
    wid, rep = weld(V2)
    assert len(rep) == 8 and np.allclose(V2[rep][wid], V2)
    t = build_topology(V2, F2)
    assert len(t) == 18 and not t.open.any() and t.flat.sum() == 6


def test_primary_edges_are_the_silhouette_from_the_camera():
    V, F = meshes.cube((1, 1, 1))
    t = build_topology(V, F)
    sil = t.primary(V, camera_origin=[0, 0, 10])  # looking straight down: the 4 top-face rim edges
    mid = (V[t.v0[sil]] + V[t.v1[sil]]) / 2
    assert len(sil) == 4 and np.allclose(mid[:, 2], 0.5)
    sil = t.primary(V, camera_origin=[10, 10, 10])  # corner view: a hexagonal outline
    assert len(sil) == 6
