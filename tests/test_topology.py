"""Edge tables: counts, classes (open, flat, concave), welding, silhouettes."""
import numpy as np

from psdr_cli.geometry import topology
from psdr_cli.geometry.topology import build_topology, face_normals, weld, winding_numbers
from psdr_cli.scene import meshes


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


def edge_set(t, rows, V):
    """Welded, unordered end points of the given rows (to compare tables of differently wound meshes)."""
    wid, _ = weld(V)
    return {tuple(sorted((wid[t.v0[r]], wid[t.v1[r]]))) for r in rows}


def test_turned_faces_do_not_change_silhouettes_or_shadow_edges():
    """Turning faces over (a mesh with inconsistent winding, or a whole solid inside out) changes
    no edge class: the table orients each closed part outward first."""
    rng = np.random.default_rng(1)
    for V, F in (meshes.cube((1, 1, 1)), meshes.torus(1.0, 0.3, 24, 12), meshes.sphere(1.0, 2)):
        t = build_topology(V, F)
        for turned in (rng.random(len(F)) < 0.3, np.ones(len(F), bool)):
            G = F.copy()
            G[turned] = G[turned, ::-1]
            u = build_topology(V, G)
            assert edge_set(u, u.secondary(), V) == edge_set(t, t.secondary(), V)
            assert edge_set(u, np.nonzero(u.concave)[0], V) == edge_set(t, np.nonzero(t.concave)[0], V)
            for cam in ([0, 0, 10], [7, -5, 3], [-2, 9, -4]):
                assert edge_set(u, u.primary(V, cam), V) == edge_set(t, t.primary(V, cam), V)
            # a flat edge between a turned and an unturned face is an image edge (a one-sided
            # material shades the turned face black)
            mixed = ~u.open & (turned[u.face0] != turned[u.face1])
            assert np.array_equal(u.turned0 != u.turned1, mixed)
            assert np.array_equal(u.turned0, turned[u.face0])  # closed parts: outward


def test_open_surface_keeps_edges_concave_on_either_side():
    """Both sides of an open surface are free space: no edge is left out as concave."""
    V, F = meshes.sphere(1.0, 2)
    V = V * (1 + 0.1 * np.sin(5 * V[:, :1]))
    keep = (V[F][:, :, 2] > -0.2).all(axis=1)
    t = build_topology(V, F[keep])
    assert t.open.any() and not t.concave.any()
    assert len(t.secondary()) == int((~t.flat).sum())


def book_mesh():
    """Three pages on the spine x ∈ [0, 1] at angles 0°, 40° and 100° in the y–z plane, wound
    every which way."""
    ang = np.radians([0.0, 40.0, 100.0])
    V = [[0, 0, 0], [1, 0, 0]] + [[0.5, np.cos(a), np.sin(a)] for a in ang]
    F = np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4]])
    return np.array(V, float), F


def test_book_spine_has_one_row_per_sector():
    V, F = book_mesh()
    t = build_topology(V, F)
    assert t.nonmanifold == 1 and t.sector.sum() == 3 and t.open.sum() == 6
    spine = np.nonzero(t.sector)[0]
    # only the 220° sector (from the 100° page round to the 0° page) bounds visibility; its
    # normals point into it, away from the 40° page
    assert list(t.secondary()) == [r for r in range(len(t)) if not t.sector[r] or not t.concave[r]]
    reflex = spine[~t.concave[spine]]
    assert len(reflex) == 1
    n0, n1 = t.normals(V)
    middle = np.array([0, np.cos(np.radians(40)), np.sin(np.radians(40))])
    assert n0[reflex[0]] @ middle < 0 and n1[reflex[0]] @ middle < 0

    def spine_rows(rows):
        return [r for r in rows if t.sector[r]]

    far = 50.0
    # a line of sight at 250°/70° passes between the pages: no silhouette; the camera at 250°
    # sits in the 220° sector and sees the crease between the 100° and 0° pages
    cam = [0.5, far * np.cos(np.radians(250)), far * np.sin(np.radians(250))]
    assert spine_rows(t.primary(V, cam)) == []
    assert spine_rows(t.creases(V, cam)) == list(reflex)
    # at 150° the line (150°/330°) has every page on one side: a silhouette
    cam = [0.5, far * np.cos(np.radians(150)), far * np.sin(np.radians(150))]
    assert spine_rows(t.primary(V, cam)) == list(reflex)
    # between the 0° and 40° pages the camera sees that sector's crease only
    cam = [0.5, far * np.cos(np.radians(20)), far * np.sin(np.radians(20))]
    rows = spine_rows(t.creases(V, cam))
    assert len(rows) == 1 and {t.face0[rows[0]], t.face1[rows[0]]} == {0, 1}


def test_edge_shared_by_two_boxes_bounds_no_visibility():
    """Two cubes touching along an edge: four faces 90° apart, so no line through it has every
    face on one side, and the edge is in no shadow-edge list."""
    Va, Fa = meshes.cube((1, 1, 1))
    V = np.vstack([Va, Va + [0, 1, 1]])
    F = np.vstack([Fa, Fa + len(Va)])
    t = build_topology(V, F)
    assert t.nonmanifold == 1 and t.sector.sum() == 4 and t.concave[t.sector].all()
    assert len(t.secondary()) == 22


def test_closed_mesh_around_a_camera_is_a_room():
    """A closed box around the camera is seen from inside: its free space is the inside, so its
    corners are concave (no line through a corner stays inside the room), however it is wound.
    The same box seen from outside has twelve convex edges."""
    V, F = meshes.cube((4, 4, 4))
    for G in (F, F[:, ::-1]):
        room = build_topology(V, G, viewpoints=[[0.3, -0.5, 0.2], [9, 9, 9]])
        assert len(room.secondary()) == 0 and room.concave.sum() == 12
        box = build_topology(V, G, viewpoints=[[9, 9, 9]])
        assert len(box.secondary()) == 12 and not box.concave.any()
    assert np.allclose(winding_numbers(V, F, [[0.1, 0.2, 0.3], [5, 0, 0]]).sum(1), [1, 0])


def test_viewpoints_outside_the_bounding_box_are_not_tested(monkeypatch):
    """Only camera origins inside a closed part's bounding box can be enclosed by it: the others
    get no winding numbers (at every iteration of an optimisation the edge table is rebuilt with
    the cameras around the object), and the table is the one built without viewpoints. A camera
    inside the box (on its boundary too) is still tested."""
    V, F = meshes.cube((4, 4, 4))
    tested = []
    real = topology.winding_numbers
    monkeypatch.setattr(topology, "winding_numbers", lambda V, F, p: tested.append(len(p)) or real(V, F, p))
    outside = build_topology(V, F, viewpoints=[[9, 9, 9], [0, 0, 2.5], [-2.01, 0, 0]])
    assert tested == [] and np.array_equal(outside.concave, build_topology(V, F).concave)
    room = build_topology(V, F, viewpoints=[[9, 9, 9], [2, 2, 2], [0.3, -0.5, 0.2]])
    assert tested == [2] and room.concave.sum() == 12


def test_edge_table_from_remembered_face_parts_is_the_fresh_one():
    """The parts and parities of a face array are remembered between builds (an optimisation
    moves vertices, the faces change at a remesh): a build with moved vertices, and one whose
    faces differ only in one face's winding (same shape), equal builds from an empty memory."""
    rng = np.random.default_rng(3)
    Vs, Fs = meshes.sphere(1.0, 2)
    Vp, Fp = meshes.plane((3.0, 3.0))
    Vb, Fb = book_mesh()
    V = np.concatenate([Vs, Vp - [0, 0, 1.5], Vb + [0, 0, 2]])
    F = np.concatenate([Fs, Fp + len(Vs), Fb + len(Vs) + len(Vp)])
    turned = F.copy()
    turned[5] = turned[5, ::-1]
    build_topology(V, F)   # remembers F's parts
    for V2, F2 in ((V + rng.normal(0, 0.02, V.shape), F), (V, turned)):
        remembered = build_topology(V2, F2)
        topology._FACE_PARTS.clear()
        fresh = build_topology(V2, F2)
        for name, value in vars(fresh).items():
            assert np.array_equal(getattr(remembered, name), value), name
    assert not np.array_equal(build_topology(V, turned).turned0, build_topology(V, F).turned0)
