"""Primary boundary term: discontinuities of the image integrand along projected edges.

The mathematics is docs/theory.md §4. With the camera vertex tied to the pixel, the pixel
integral changes only where its integrand jumps across a moving curve: the projected silhouettes
of the moving meshes, every non-flat edge of a flat-shaded mesh (the shading normal jumps
there), and of a smooth-shaded one when light scatters at the camera vertex (§8). For an edge
point q(θ) with screen normal n_s,

    dI/dθ = ∫_edges (n_s · q̇) [L(q − ε n_s) − L(q + ε n_s)] dl,

estimated by drawing an edge ∝ w_e·ℓ_e (ℓ_e its projected length in pixels) and a uniform point
on it, the N draws of a pass stratified along the cumulative mass (:func:`stratified`); each
sample adds (1/N)·[(n_s·q(θ)) ΔL / p(q) − detach(·)] to the pixel of q. The edge
weights w_e of ``primary_sampling`` (``length``: all 1; ``jump``: inner creases of flat-shaded
meshes weighted by their normal angle, :data:`JUMP_ANGLE`, :data:`JUMP_MIN_WEIGHT`), why any
w_e > 0 is unbiased and when ``jump`` lowers the variance are in §4.

Parameters (experiment keys)
----------------------------
``estimator.terms`` (list of term names, default all four)
    The term runs when ``primary`` is listed.
``estimator.primary_spp`` (int ≥ 1, default 16)
    Edge samples per pixel: primary_spp·W·H per view.
``estimator.primary_sampling`` (``length`` | ``jump``, default ``length``)
    Edge density: ∝ projected length, or inner creases of flat-shaded meshes down-weighted (§4).
``scene.max_depth`` (int ≥ 1, default 2)
    Depth of the radiance read on the two sides of an edge (:func:`.interior.radiance`).
``scene.objects[].edges`` (bool, default true)
    Only these objects' edges are image-discontinuity curves.
``scene.objects[].smooth`` (bool, default false)
    Flat-shaded meshes contribute every non-flat edge; smooth-shaded ones their silhouettes,
    and their inner edges too when ``max_depth`` ≥ 2.
``estimator.passes`` (int ≥ 1, default 1)
    Fewest passes each view's samples are split into (more when a pass would exceed
    :data:`.passes.AD_LANES` lanes).

The term is never guided (``estimator.guiding`` does not apply).
"""
from __future__ import annotations

import hashlib

import drjit as dr
import mitsuba as mi
import numpy as np

from dataclasses import dataclass

from . import interior
from ..geometry.intersections import Segments, intersection_segments, segment_points
from ..geometry.topology import face_normals
from ..support.jitarray import concat, jit_array
from .boundary_sampling import BoundaryEdges, sensor_origins
from .camera import CameraTable, LaneCameras, Projection, SensorCamera, film_pixel, sensor_groups
from .term import Term, boundary_pass

#: Offset of the two radiance samples from the edge, as a fraction of the image's larger side
#: (6.4e-5 px at 32 px, 1e-3 px at 512 px: ≥ 16 float32 ulps of the pixel coordinate). The
#: difference of the two samples is the jump plus 2·offset·∂L/∂n, and ∂L/∂n is steep next to a
#: silhouette (grazing faces), so the offset is small (docs/gradients.md). Intersection curves
#: move their side samples out of the ray-spawn band around the curve (crossing_offsets).
SIDE_EPS = 2e-6
#: Relative depth within which a foreign hit counts as "at the edge" (a neighbour face sharing an
#: end point of the edge, hit by a side ray near that end point).
DEPTH_TOL = 1e-3
#: Face-normal angle (radians, ~14°) from which an inner crease is sampled as densely per pixel
#: of length as a silhouette (``primary_sampling: jump``).
JUMP_ANGLE = 0.25
#: Smallest relative sampling density of an inner crease (``primary_sampling: jump``).
JUMP_MIN_WEIGHT = 0.1


def jump_weights(topo, V, rows, inner, smooth: bool, normals=None) -> np.ndarray:
    """Sampling weight w_e per edge row (``primary_sampling: jump``, see the module docstring):
    clamp(φ_e / JUMP_ANGLE, JUMP_MIN_WEIGHT, 1) on the inner edges of a flat-shaded mesh whose
    faces are both unturned (φ_e = angle between n0 and n1), 1 elsewhere."""
    w = np.ones(len(rows))
    if smooth or not len(rows):
        return w
    n0, n1 = topo.normals(V) if normals is None else normals
    n0, n1 = n0[rows], n1[rows]
    phi = np.arctan2(np.linalg.norm(np.cross(n0, n1), axis=1), np.einsum("ij,ij->i", n0, n1))
    crease = inner & ~topo.turned0[rows] & ~topo.turned1[rows] & ~topo.open[rows]
    w[crease] = np.clip(phi[crease] / JUMP_ANGLE, JUMP_MIN_WEIGHT, 1.0)
    return w


def primary_edge_ids(edges: BoundaryEdges, V: np.ndarray, camera_origin, scattering: bool = True,
                     sampling: str = "length", normals=None):
    """(v0, v1, face0, face1, mesh index, strict, inner, weight) of the edges that can carry an
    image discontinuity for this camera (vertex ids into ``V``, faces per mesh; face1 = face0 on
    open edges): the rows of :meth:`psdr_cli.geometry.topology.Topology.creases` (non-flat edges, and flat
    edges between a turned and an unturned face, with at least one face showing its front to the
    camera: an edge between two back faces of a closed mesh is never seen, and near a silhouette
    it projects just behind a grazing front face).

    Smooth-shaded meshes need their inner edges too when light scatters at the camera vertex
    (``scattering``: max_depth ≥ 2): the pixel value is continuous in the shading normal, but the
    light a vertex receives is cut at its facet's plane (the terminator), and that plane turns
    from face to face, so near the terminator the image jumps across every edge. ``strict`` (both sides must see the edge)
    holds for all but smooth silhouettes (see docs/gradients.md); ``inner`` marks edges whose two
    faces both face the camera; ``weight`` is the edge's sampling weight w_e (:func:`jump_weights`,
    all 1 with ``sampling`` = ``length``). ``normals``: each mesh's row normals (:func:`mesh_normals`)
    when already computed for these vertices."""
    normals = mesh_normals(edges, V) if normals is None else normals
    cols = [[] for _ in range(10)]
    for m, (topo, offset, smooth) in enumerate(edges.meshes):
        Vo = V[offset: offset + int(topo.faces.max()) + 1]
        sel = topo.creases(Vo, camera_origin, normals[m])
        silhouette = topo.primary(Vo, camera_origin, normals[m])
        if smooth and not scattering:
            sel = silhouette
        inner = ~np.isin(sel, silhouette)
        strict = inner if smooth else np.ones(len(sel), bool)
        f1 = np.where(topo.open, topo.face0, topo.face1)
        weight = jump_weights(topo, Vo, sel, inner, smooth, normals[m]) if sampling == "jump" else np.ones(len(sel))
        n0, n1 = fold_normals(topo, Vo, sel, normals[m])
        for c, arr in zip(cols, (topo.v0[sel] + offset, topo.v1[sel] + offset, topo.face0[sel], f1[sel],
                                 np.full(len(sel), m), strict, inner, weight, n0, n1)):
            c.append(arr)
    if not cols[0]:
        return [np.zeros(0, np.int64)] * 7 + [np.zeros(0)] + [np.zeros((0, 3))] * 2
    return [np.concatenate(c).astype(np.int64) for c in cols[:7]] + [np.concatenate(c) for c in cols[7:]]


def mesh_normals(edges: BoundaryEdges, V: np.ndarray) -> list:
    """(n0, n1) of every edge row of each edge object (:meth:`psdr_cli.geometry.topology.Topology.normals`),
    its vertices in ``V``: they depend on the vertices only, not on the camera."""
    return [topo.normals(V[offset: offset + int(topo.faces.max()) + 1]) for topo, offset, _ in edges.meshes]


def fold_normals(topo, V, rows, normals=None):
    """(n0, n1) per edge row: the row's consistently oriented face normals where they are more
    than 90° apart (n0·n1 < 0: the faces fold back, as at a thin ear or a sharp brow), zero on
    every other row and on open edges (:func:`fold_offsets` moves side samples only there)."""
    n0, n1 = (x[rows] for x in (topo.normals(V) if normals is None else normals))
    fold = ~topo.open[rows] & (np.einsum("ij,ij->i", n0, n1) < 0)
    return np.where(fold[:, None], n0, 0.0), np.where(fold[:, None], n1, 0.0)


@dataclass
class Curves:
    """Image-discontinuity curves as segments p0(θ)p1(θ) (AD), each with the two faces it bounds:
    (shape0, face0) and (shape1, face1), shapes as Mitsuba registry ids (as in ``si.shape``)."""
    p0: mi.Point3f
    p1: mi.Point3f
    shape0: np.ndarray
    face0: np.ndarray
    shape1: np.ndarray
    face1: np.ndarray
    strict: np.ndarray  # visibility needs both sides (flat creases, intersections), else one side
    inner: np.ndarray  # both faces face the camera: each side must land on the curve's surface
    #: unit normals (n, 3) of face0 and face1 on intersection curves, zero on mesh edges
    normal0: np.ndarray = None
    normal1: np.ndarray = None
    #: sampling weight w_e per curve (module docstring); 1 when not given
    weight: np.ndarray = None
    #: unit normals (n, 3) of the two faces of mesh edges whose faces fold by more than 90°
    #: (:func:`fold_normals`), zero elsewhere
    fold0: np.ndarray = None
    fold1: np.ndarray = None

    def __post_init__(self):
        for name in ("normal0", "normal1", "fold0", "fold1"):
            if getattr(self, name) is None:
                setattr(self, name, np.zeros((len(self.face0), 3)))
        if self.weight is None:
            self.weight = np.ones(len(self.face0))

    def __len__(self):
        return len(self.face0)


def shape_id(shape) -> int:
    """Mitsuba registry id of a shape (what ``dr.reinterpret_array(mi.UInt32, si.shape)`` gives)."""
    return int(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(shape))[0])


def concat_points(a: mi.Point3f, b: mi.Point3f) -> mi.Point3f:
    if dr.width(a) == 0:
        return b
    if dr.width(b) == 0:
        return a
    return concat([a, b])


#: The columns :func:`primary_edge_ids` returns, in its order.
EDGE_ID_COLUMNS = ("v0", "v1", "face0", "face1", "mesh", "strict", "inner", "weight", "fold0", "fold1")


def camera_edge_ids(edges: BoundaryEdges, P, camera_origin, scattering: bool, sampling: str) -> dict:
    """:func:`primary_edge_ids` by column name (:data:`EDGE_ID_COLUMNS`) for the vertex buffer
    ``P`` (read to the host and its row normals computed once for the views of a pass)."""
    V = edges.remembered("vertices", [P], lambda: np.asarray(dr.detach(P), np.float64).reshape(-1, 3))
    normals = edges.remembered("normals", [P], lambda: mesh_normals(edges, V))
    return dict(zip(EDGE_ID_COLUMNS, primary_edge_ids(edges, V, camera_origin, scattering, sampling, normals)))


def edge_shape_ids(scene: mi.Scene, edges: BoundaryEdges) -> np.ndarray:
    """The Mitsuba registry id (:func:`shape_id`) of each edge object, in the order of ``edges.names``."""
    shapes = {s.id(): s for s in scene.shapes()}
    return np.array([shape_id(shapes[n]) for n in edges.names], np.int64)


def mesh_edge_curves(scene: mi.Scene, edges: BoundaryEdges, P, camera_origin, scattering: bool,
                     sampling: str = "length") -> Curves:
    """Primary mesh edges of the edge objects (see :func:`primary_edge_ids`)."""
    c = camera_edge_ids(edges, P, camera_origin, scattering, sampling)
    ids = edge_shape_ids(scene, edges)[c["mesh"]] if len(c["mesh"]) else c["mesh"]
    gather = lambda i: dr.gather(mi.Point3f, P, jit_array(mi.UInt32, i))  # noqa: E731
    return Curves(gather(c["v0"]), gather(c["v1"]), ids, c["face0"], ids, c["face1"], c["strict"].astype(bool),
                  c["inner"].astype(bool), weight=c["weight"], fold0=c["fold0"], fold1=c["fold1"])


def mesh_shapes(scene: mi.Scene, names) -> list:
    """Every triangle mesh of the scene: the edge objects ``names`` first, in that order."""
    shapes = {s.id(): s for s in scene.shapes() if isinstance(s, mi.Mesh)}
    return [shapes[n] for n in names if n in shapes] + [s for n, s in shapes.items() if n not in names]


def mesh_arrays(positions, faces) -> list:
    """(V, F) as float64 (n, 3) and int64 (m, 3) numpy arrays of flat vertex and face buffers."""
    return [(np.asarray(p, np.float64).reshape(-1, 3), np.asarray(f, np.int64).reshape(-1, 3))
            for p, f in zip(positions, faces)]


def scene_meshes(scene: mi.Scene, edges: BoundaryEdges, P):
    """Every triangle mesh of the scene as (shape, V, F) (:func:`mesh_shapes`) plus one flat
    vertex buffer of all of them: the edge objects' part is ``P`` (AD), the others are constants."""
    shapes = mesh_shapes(scene, edges.names)
    positions = [dr.detach(s.vertex_positions_buffer()) for s in shapes]
    faces = [s.faces_buffer() for s in shapes]
    arrays = edges.remembered("meshes", positions + faces, lambda: mesh_arrays(positions, faces))
    moving = sum(s.id() in edges.names for s in shapes)
    bufs = [mi.Float(p) for p in positions[moving:]]
    buf = P if not bufs else dr.concat([P] + bufs)
    return [(s, V, F) for s, (V, F) in zip(shapes, arrays)], buf, moving


def segments_key(arrays) -> str:
    """Digest of every (V, F) of ``arrays``: the geometry an intersection search was run on."""
    digest = hashlib.blake2b(digest_size=16)
    for V, F in arrays:
        digest.update(np.ascontiguousarray(V).tobytes())
        digest.update(np.ascontiguousarray(F).tobytes())
    return digest.hexdigest()


def scene_segments(edges: BoundaryEdges, meshes) -> Segments:
    """Intersection segments of ``meshes`` ((shape, V, F) each), searched once per geometry: the
    result is kept in ``edges.segments`` under :func:`segments_key`, so the views of one
    iteration (same vertices) share one search, and a search run ahead
    (:mod:`psdr_cli.optimisation.geometry_ahead`) is found there."""
    key = segments_key([(V, F) for _, V, F in meshes])
    if key not in edges.segments:
        edges.segments.clear()
        edges.segments[key] = intersection_segments([V for _, V, _ in meshes], [F for _, _, F in meshes])
    return edges.segments[key]


def moving_segments(scene: mi.Scene, edges: BoundaryEdges, P) -> tuple:
    """(meshes, segments, keep): the scene's meshes (:func:`scene_meshes`), their intersection
    segments (:func:`scene_segments`) and which of them involve at least one edge object."""
    with dr.suspend_grad():
        meshes, _, n_moving = scene_meshes(scene, edges, P)
    seg = scene_segments(edges, meshes)
    return meshes, seg, (seg.mesh < n_moving).any(1)


def crossing_count(scene: mi.Scene, edges: BoundaryEdges, P) -> int:
    """Number of intersection curves :func:`intersection_curves` would return."""
    return int(moving_segments(scene, edges, P)[2].sum())


def intersection_curves(scene: mi.Scene, edges: BoundaryEdges, P) -> Curves:
    """Intersection curves that involve at least one edge object (:mod:`psdr_cli.geometry.intersections`)."""
    meshes, seg, keep = moving_segments(scene, edges, P)
    empty = np.zeros(0, np.int64)
    if not keep.any():
        return Curves(mi.Point3f(), mi.Point3f(), empty, empty, empty, empty, empty.astype(bool), empty.astype(bool))
    seg = Segments(seg.ends[keep], seg.mesh[keep], seg.face[keep])
    _, buf, _ = scene_meshes(scene, edges, P)
    p0, p1 = segment_points(buf, seg)
    ids = np.array([shape_id(s) for s, _, _ in meshes], np.int64)
    normals = [curve_face_normals(meshes, seg.mesh[:, j], seg.face[:, j]) for j in (0, 1)]
    return Curves(p0, p1, ids[seg.mesh[:, 0]], seg.face[:, 0], ids[seg.mesh[:, 1]], seg.face[:, 1],
                  np.ones(len(seg), bool), np.zeros(len(seg), bool), *normals)


def curve_face_normals(meshes, mesh, face):
    """Unit normals (n, 3) of faces ``face`` of meshes ``mesh`` (indices into (shape, V, F))."""
    out = np.zeros((len(face), 3))
    for m, (_, V, F) in enumerate(meshes):
        sel = mesh == m
        out[sel] = face_normals(V, F[face[sel]])
    return out


def primary_curves(scene: mi.Scene, edges: BoundaryEdges, P, camera_origin, scattering: bool = True,
                   sampling: str = "length") -> Curves:
    """Mesh edges and intersection curves, concatenated."""
    a = mesh_edge_curves(scene, edges, P, camera_origin, scattering, sampling)
    b = intersection_curves(scene, edges, P)
    if len(b) == 0:
        return a
    return Curves(concat_points(a.p0, b.p0), concat_points(a.p1, b.p1),
                  *(np.concatenate([getattr(a, k), getattr(b, k)])
                    for k in ("shape0", "face0", "shape1", "face1", "strict", "inner", "normal0", "normal1",
                              "weight", "fold0", "fold1")))


def gather_curve_points(q: mi.Point2f, k: mi.UInt32) -> mi.Point2f:
    """q[k] for the projected end points q of the curves (AD). Its reverse-mode scatter goes into
    an array as wide as the curve list, which is small, so Dr.Jit's automatic choice would expand
    it into per-thread copies indexed thread·n + k with n (different every iteration) a literal
    of the kernel, compiled again every iteration; a local pre-reduction (``ReduceMode.Local``)
    has no such constant."""
    return dr.gather(mi.Point2f, q, k, mode=dr.ReduceMode.Local)


def edge_depth(ray, p0, p1):
    """Distance along ``ray`` to the point of the line p0p1 closest to it (the edge under q)."""
    e = p1 - p0
    w = ray.o - p0
    b = dr.dot(ray.d, e)
    c = dr.squared_norm(e)
    denom = c - b * b  # ray.d is unit length
    return (b * dr.dot(w, e) - c * dr.dot(ray.d, w)) / dr.select(denom > 0, denom, 1.0)


def edge_visible(scene, rays, segment, own, strict, inner, active, *, hits=None):
    """Whether the camera sees the curve point under q: on *both* sides of it (``strict``: flat
    creases and intersection curves; otherwise — smooth silhouettes — on at least one side) the
    first hit is one of the curve's own faces, or lies behind the curve (or is a miss). On an
    ``inner`` edge (both faces towards the camera) a side must hit the surface at the edge: one of
    its faces or a face at its depth (a neighbour sharing an end point). A miss or a farther hit
    there means the face on that side is thinner than the side offset, next to a silhouette edge
    that already carries this discontinuity (accepting it would count the silhouette twice).

    A point counts as hidden as soon as one side hits a foreign surface in front of it: accepting
    a point seen from one side only would let through hidden edges next to a silhouette, just
    behind a grazing front face, and over-count silhouette pixels of dense flat meshes by up to
    2×. ``segment`` = (p0, p1) the curve's end points; ``own`` = (shape0, face0, shape1, face1) as
    UInt32 arrays. ``hits``: the first hits of ``rays`` if already traced (with the mask ``active``)."""
    t_edge = edge_depth(rays[0], *segment)
    every, some = mi.Bool(True), mi.Bool(False)
    for i, ray in enumerate(rays):
        si = scene.ray_intersect(ray, active) if hits is None else hits[i]
        mine = is_own_face(si, own)
        at_edge = si.is_valid() & (dr.abs(si.t - t_edge) <= t_edge * DEPTH_TOL)
        behind = ~si.is_valid() | (si.t > t_edge * (1.0 - DEPTH_TOL))
        side = mine | dr.select(inner, at_edge, behind)
        every &= side
        some |= side
    return active & dr.select(strict, every, some)


#: Distance of an intersection curve's side samples from the other surface's plane, in units of
#: the largest distance at which a ray spawned from the side's hit point would start behind that
#: plane (see :func:`crossing_offsets`).
CROSSING_MARGIN = 2.0
#: Largest image offset of an intersection curve's side samples, as a fraction of the image's
#: larger side (reached only where the two surfaces are nearly tangent).
CROSSING_MAX_EPS = 1e-4
#: Distance of a folded mesh edge's side samples from the other face's plane, in units of the
#: largest distance at which a spawned ray starts beyond it (see :func:`fold_offsets`).
FOLD_MARGIN = 2.0
#: Largest image offset of a folded mesh edge's side samples, as a fraction of the image's larger
#: side.
FOLD_MAX_EPS = 1e-4


def hits_shape(si, sid: int):
    """Whether hits ``si`` are valid and on the shape with registry id ``sid``."""
    return si.is_valid() & (dr.reinterpret_array(mi.UInt32, si.shape) == sid)


def is_own_face(si, own):
    """Whether hits ``si`` are on face (own[0], own[1]) or (own[2], own[3]) (shape id, prim index)."""
    sid = dr.reinterpret_array(mi.UInt32, si.shape)
    return ((sid == own[0]) & (si.prim_index == own[1])) | ((sid == own[2]) & (si.prim_index == own[3]))


def lands_on_own_face(scene, ray, own, active):
    """Whether ``ray`` first hits face (own[0], own[1]) or (own[2], own[3])."""
    si = scene.ray_intersect(ray, active)
    return si.is_valid() & is_own_face(si, own)


@dataclass
class SidePoints:
    """Curve points as their two side samples see them: the film positions q (detached, pixels),
    the screen normals n_s (the sides lie at q ± offset·n_s), a 3D point x of each curve and its
    two faces ``own`` = (shape0, face0, shape1, face1) as UInt32 arrays."""
    q: mi.Point2f
    n_s: mi.Vector2f
    x: mi.Point3f
    own: list


def crossing_offsets(scene, cameras, points: SidePoints, normals, size: int, active):
    """Signed image offsets (−a, +b) of the two side samples of intersection-curve ``points`` (the
    default ±SIDE_EPS·``size`` elsewhere: n0 = 0; ``size`` the film's larger side, pixels).

    A ray leaving a surface point p starts at p + m·n, m = (1 + max|p|)·RayEpsilon (Mitsuba's
    ``spawn_ray``, n the facet normal on the ray's side). Next to an intersection curve the other
    surface's plane passes within m of p, and where the two normals point apart (a sharp crease)
    that start point lies behind it: inside the other solid, where every ray from it is blocked.
    A side sample at the default offset can fall in that band and read a radiance of 0 (or a
    partly blocked one; the band's measured width is in docs/gradients.md). So each side moves out until its plane point lies CROSSING_MARGIN·m·max(0,
    −n_o·n_p) from the other plane (n_p the seen face's normal towards the camera, n_o the other
    face's towards p), found from the two planes through the curve (x a point of it,
    ``normals`` = (n0, n1) theirs) without tracing, and at most CROSSING_MAX_EPS·size. Only where
    both sides at the default offset land on the curve's own faces (own): a crease hidden a
    hair behind another surface (accepted by the depth tolerance of :func:`edge_visible`) keeps
    the default, where both sides read that surface and the jump is 0. ``cameras(uv, active)``
    gives each lane's camera ray (:class:`.camera.SensorCamera`, :class:`.camera.LaneCameras`)."""
    q, n_s, x, own = points.q, points.n_s, points.x, points.own
    n0, n1 = normals
    base = SIDE_EPS * size
    cap = CROSSING_MAX_EPS * size
    crossing = dr.squared_norm(n0) > 0
    for sign in (-1.0, 1.0):
        crossing &= lands_on_own_face(scene, cameras(q + sign * base * n_s, active), own, active & crossing)
    out = []
    for sign in (-1.0, 1.0):
        ray = cameras(q + sign * cap * n_s, active)  # planes: distances ∝ offset
        t0 = dr.dot(n0, x - ray.o) / dr.dot(n0, ray.d)
        t1 = dr.dot(n1, x - ray.o) / dr.dot(n1, ray.d)
        first = (t0 > 0) & ((t0 <= t1) | ~(t1 > 0))  # a concave crease: the nearer plane is seen
        t = dr.select(first, t0, t1)
        n_p = dr.select(first, n0, n1)
        n_o = dr.select(first, n1, n0)
        p = ray.o + t * ray.d
        n_p = dr.mulsign(n_p, -dr.dot(n_p, ray.d))  # towards the camera
        dist = dr.dot(n_o, p - x)  # grows linearly with the offset, from 0 on the curve
        n_o = dr.mulsign(n_o, dist)
        m = (1.0 + dr.max(dr.abs(p))) * mi.math.RayEpsilon
        need = CROSSING_MARGIN * m * dr.maximum(-dr.dot(n_o, n_p), 0.0)
        offset = dr.minimum(dr.maximum(cap * need / dr.maximum(dr.abs(dist), 1e-30), base), cap)
        out.append(sign * dr.select(crossing & (t > 0), offset, base))
    return out


def fold_offsets(scene, cameras, points: SidePoints, normals, size: int, offsets, active):
    """Signed image offsets of the two side samples of mesh-edge ``points`` whose faces fold by
    more than 90° (``normals`` = (n0, n1): the faces' consistently oriented normals,
    :func:`fold_normals`; zero elsewhere, where ``offsets`` are kept; ``size`` the film's larger
    side, pixels).

    A ray leaving a point p of face a starts at p ± m·n_a, m = (1 + max|p|)·RayEpsilon (Mitsuba's
    ``spawn_ray``, the sign that of n_a·ω). Within m·(−n_a·n_b) of the edge that start lies beyond
    the plane of the other face b, so rays that face b blocks escape it (or rays it does not block
    start behind it). For a flat face only directions below its own plane leak, and those carry no
    reflectance; a smooth face's shading normal reflects part of them, so a side read at the
    default offset inside that band is the wrong radiance (the band's measured width is in
    docs/gradients.md). A side that lands on one of the edge's faces at the
    default offset moves out until its point on that face's plane lies FOLD_MARGIN·m·(−n_a·n_b)
    from the other face's plane, at most FOLD_MAX_EPS of the image size; a side that lands
    elsewhere (beyond a silhouette) keeps its offset."""
    q, n_s, x, own = points.q, points.n_s, points.x, points.own
    n0, n1 = normals
    base = SIDE_EPS * size
    cap = FOLD_MAX_EPS * size
    fold = dr.squared_norm(n0) > 0
    c = dr.maximum(-dr.dot(n0, n1), 0.0)
    out = []
    for sign, default in zip((-1.0, 1.0), offsets):
        si = scene.ray_intersect(cameras(q + sign * base * n_s, active), active & fold)
        sid = dr.reinterpret_array(mi.UInt32, si.shape)
        on0 = si.is_valid() & (sid == own[0]) & (si.prim_index == own[1])
        on1 = si.is_valid() & (sid == own[2]) & (si.prim_index == own[3])
        n_p = dr.select(on0, n0, n1)
        n_o = dr.select(on0, n1, n0)
        ray = cameras(q + sign * cap * n_s, active)  # distances ∝ offset
        t = dr.dot(n_p, x - ray.o) / dr.dot(n_p, ray.d)
        p = ray.o + t * ray.d
        dist = dr.abs(dr.dot(n_o, p - x))
        m = (1.0 + dr.max(dr.abs(p))) * mi.math.RayEpsilon
        offset = dr.minimum(dr.maximum(cap * FOLD_MARGIN * m * c / dr.maximum(dist, 1e-30), base), cap)
        out.append(dr.select(fold & (on0 | on1) & (t > 0), sign * offset, default))
    return out


@dataclass
class CurveTable:
    """What a lane reads of the curve it drew, as Dr.Jit arrays (one entry per curve): the end
    points p0, p1 (AD), the two faces' (shape id, face index), ``strict`` and ``inner``
    (:class:`Curves`), the sampling weight w_e, the faces' normals on intersection curves
    (``normal0``, ``normal1``) and on folded mesh edges (``fold0``, ``fold1``), zero elsewhere.
    ``crossings`` and ``folds`` say whether any curve has such normals (the side offsets of
    :func:`crossing_offsets` and :func:`fold_offsets` are traced only then)."""
    p0: mi.Point3f
    p1: mi.Point3f
    shape0: mi.UInt32
    face0: mi.UInt32
    shape1: mi.UInt32
    face1: mi.UInt32
    strict: mi.Bool
    inner: mi.Bool
    weight: mi.Float
    normal0: mi.Vector3f
    normal1: mi.Vector3f
    fold0: mi.Vector3f
    fold1: mi.Vector3f
    crossings: bool
    folds: bool


def vectors(a: np.ndarray) -> mi.Vector3f:
    """An (n, 3) numpy array as a ``mi.Vector3f``."""
    return mi.Vector3f(*(jit_array(mi.Float, a[:, i]) for i in range(3)))


def curve_table(curves: Curves) -> CurveTable:
    """The columns of ``curves`` (numpy) uploaded as a :class:`CurveTable`."""
    ints = [jit_array(mi.UInt32, getattr(curves, a)) for a in ("shape0", "face0", "shape1", "face1")]
    return CurveTable(curves.p0, curves.p1, *ints, jit_array(mi.Bool, curves.strict),
                      jit_array(mi.Bool, curves.inner), jit_array(mi.Float, curves.weight),
                      *(vectors(getattr(curves, a)) for a in ("normal0", "normal1", "fold0", "fold1")),
                      bool(np.any(curves.normal0)), bool(np.any(curves.fold0)))


def curve_mass(q0, q1, z0, z1, near, weight) -> mi.Float:
    """Sampling mass w_e·ℓ_e of curves with projected end points q0, q1 (pixels) at camera depths
    z0, z1: 0 unless both ends lie before the near plane (detached)."""
    with dr.suspend_grad():
        front = (dr.detach(z0) > near) & (dr.detach(z1) > near)
        return dr.select(front, weight * dr.norm(dr.detach(q1 - q0)), 0.0)


def join_curves(parts) -> Curves:
    """The curves of several views end to end (curve k of view j is curve k + Σ_{i<j} n_i)."""
    if len(parts) == 1:
        return parts[0]
    return Curves(concat([c.p0 for c in parts]), concat([c.p1 for c in parts]),
                  *(np.concatenate([getattr(c, k) for c in parts])
                    for k in ("shape0", "face0", "shape1", "face1", "strict", "inner", "normal0", "normal1",
                              "weight", "fold0", "fold1")))


@dataclass
class Draw:
    """Each lane's curve draw: curve index k (into the joined curves), position s ∈ [0, 1) along
    it, the scale Σ_e w_e·ℓ_e / N of its view (1/(N·p(q)) = scale / w_k) and whether it drew one."""
    k: mi.UInt32
    s: mi.Float
    scale: mi.Float
    alive: mi.Bool


#: Bisection steps of a curve draw (:func:`draw_views`): enough for 2^24 curves per view.
DRAW_STEPS = 24


def stratified(u: mi.Float, n_samples: int, view=None) -> mi.Float:
    """The curve draw's uniforms, one per stratum: lane j of a view's N = ``n_samples`` lanes
    (j = i − view·N for lane i) takes (j + u_j) / N, uniform in [j/N, (j + 1)/N). Inverting the
    cumulative mass at stratified points is unbiased like independent draws (each stratum is
    drawn once with probability 1/N) and leaves less variance; consecutive lanes then draw
    neighbouring points of the curve list, so their rays stay coherent (docs/theory.md §4;
    measured in docs/benchmarks/iteration_time.md)."""
    lane = dr.arange(mi.UInt32, dr.width(u))
    if view is not None:
        lane -= view * dr.opaque(mi.UInt32, n_samples)
    return dr.minimum((mi.Float(lane) + u) * (1.0 / n_samples), dr.one_minus_epsilon(mi.Float))


def draw_views(mass: mi.Float, start: mi.UInt32, count: mi.UInt32, view, u: mi.Float, n_samples: int) -> Draw:
    """Curves drawn per lane among its own view's, on the device: ``mass`` holds the joined curves'
    masses w_e·ℓ_e (view j's are the ``count[j]`` entries from ``start[j]``; entries of no view may
    follow), lane i belongs to view ``view[i]`` (None: view 0). With C_j the cumulative mass (an
    exclusive prefix sum in float64 over the whole array, B_v = C at the view's first curve) and
    T_v its view's total, the lane finds the first j of its view's range with C_j + m_j > B_v + u·T_v
    by bisection and s = (B_v + u·T_v − C_j) / m_j; a lane whose view has no mass draws nothing
    (``alive`` false). The bisection takes :data:`DRAW_STEPS` steps whatever the counts (up to
    2^DRAW_STEPS curves per view): one kernel for every count, and no value read to the host."""
    view = dr.zeros(mi.UInt32, dr.width(u)) if view is None else view
    before = dr.prefix_sum(mi.Float64(mass))
    after = before + mi.Float64(mass)
    lo = dr.gather(mi.UInt32, start, view)
    size = dr.gather(mi.UInt32, count, view)
    has = size > 0
    last = dr.select(has, lo + size - 1, 0)
    base = dr.gather(mi.Float64, before, lo, has)
    total = dr.gather(mi.Float64, after, last, has) - base
    x = base + mi.Float64(u) * total
    for _ in range(DRAW_STEPS):  # first j in [lo, lo + size) with C_j + m_j > x
        half = size >> 1
        right = (size > 0) & (dr.gather(mi.Float64, after, lo + half, size > 0) <= x)
        lo = dr.select(right, lo + half + 1, lo)
        size = dr.select(right, size - half - 1, half)
    k = dr.select(has, dr.minimum(lo, last), 0)
    m = dr.gather(mi.Float, mass, k, has)
    alive = has & (total > 0) & (m > 0)
    s = mi.Float((x - dr.gather(mi.Float64, before, k, has)) / dr.select(m > 0, mi.Float64(m), 1.0))
    s = dr.clip(s, 0.0, dr.one_minus_epsilon(mi.Float))
    return Draw(k, s, mi.Float(total) / n_samples, alive)


def drawable(counts) -> np.ndarray:
    """``counts`` (curves per view) as an array, refused beyond 2^DRAW_STEPS − 1 curves in a view
    (what :func:`draw_views` can draw from)."""
    counts = np.asarray(counts, np.int64)
    if counts.size and counts.max() >> DRAW_STEPS:
        raise ValueError(f"primary term: {int(counts.max())} curves in one view; at most 2^{DRAW_STEPS} - 1")
    return counts


def view_starts(counts) -> np.ndarray:
    """Where each view's curves start in the joined list (``counts`` per view): their exclusive prefix sum."""
    return np.concatenate([[0], np.cumsum(counts, dtype=np.int64)[:-1]])


def view_ranges(counts) -> tuple:
    """(start, count) of each view's curves in the joined list (``counts`` per view), as UInt32 arrays."""
    counts = drawable(counts)
    return jit_array(mi.UInt32, view_starts(counts)), jit_array(mi.UInt32, counts)


@dataclass(frozen=True)
class SideReading:
    """What the two side samples of a curve point read, and on which film: the W × H film
    (pixels), the radiance of paths up to ``max_depth`` (the far side of a silhouette against
    the sky reading 0 with ``hide_background``) or, with ``coverage`` a shape's registry id
    (:func:`shape_id`), the indicator that the camera ray's first hit is on that shape."""
    width: int
    height: int
    max_depth: int
    hide_background: bool = False
    coverage: int | None = None


@dataclass
class CurveCameras:
    """The cameras of a pass over curves: ``cameras(uv, active)`` each lane's camera ray
    (:class:`.camera.SensorCamera` for one view, :class:`.camera.LaneCameras`), ``view`` each
    lane's view (None: one view) and ``projector`` what projects the curves' end points
    (:class:`.camera.Projection`, or :class:`.camera.LaneCameras` with each curve's camera)."""
    cameras: object
    view: mi.UInt32 | None
    projector: object


def primary_boundary(scene: mi.Scene, sensor: mi.Sensor, edges: BoundaryEdges, P, n_samples: int,
                     sampler: mi.Sampler, max_depth: int, *, sampling: str = "length", hide_background: bool = False,
                     coverage: int | None = None):
    """Primary boundary contribution (flat W·H·3 image, primal 0) from ``n_samples`` curve points
    (mesh edges and intersection curves), edges drawn ∝ w_e·ℓ_e (``sampling``: module docstring);
    ``hide_background``: the far side of a silhouette against the sky reads 0, as the interior
    term's camera rays do (:func:`.interior.radiance`); ``coverage``: a shape's registry id
    (:func:`shape_id`): the jump of the indicator that a camera ray's first hit is on that shape,
    instead of the radiance's (:mod:`.coverage`)."""
    return views_primary_boundary(scene, [sensor], edges, P, n_samples, sampler, max_depth, sampling=sampling,
                                  hide_background=hide_background, coverage=coverage)[0]


def views_primary_boundary(scene: mi.Scene, sensors, edges: BoundaryEdges, P, n_samples: int, sampler: mi.Sampler,
                           max_depth: int, *, sampling: str = "length", hide_background: bool = False,
                           coverage: int | None = None) -> list:
    """:func:`primary_boundary` of several views (one film size) traced as one wavefront: lane i
    (``n_samples`` per view, ``sampler`` as wide as all of them) belongs to view i // n_samples of
    ``sensors``, draws a point of that view's curves (:func:`draw_views`) and casts that view's
    camera rays; each view's curves are projected into its camera (:class:`.camera.LaneCameras`
    for several views, rays and projections from one camera table: the arithmetic of the recorded
    part, :mod:`psdr_cli.optimisation.frozen_batch`); one image per view. One view is the per-view pass."""
    width, height = (int(s) for s in sensors[0].film().size())
    count = len(sensors)
    images = [dr.zeros(mi.Float, width * height * 3) for _ in sensors]
    if edges.count == 0 and not edges.meshes:
        return images
    origins = sensor_origins(sensors)
    parts = [None] * count  # a sensor listed several times (passes of one view) selects its curves once
    for group in sensor_groups(sensors):
        curves = primary_curves(scene, edges, P, origins[group[0]], max_depth >= 2, sampling)
        for k in group:
            parts[k] = curves if len(curves) else None
    live = [c for c in parts if c is not None]
    if not live:
        return images
    curves = join_curves(live)
    if count == 1:
        views = CurveCameras(SensorCamera(sensors[0], width, height), None, Projection(sensors[0]))
    else:
        table = CameraTable.of(sensors, width, height)
        view = dr.arange(mi.UInt32, n_samples * count) // dr.opaque(mi.UInt32, n_samples)
        owner = np.repeat(np.arange(count), [len(c) if c is not None else 0 for c in parts])
        views = CurveCameras(LaneCameras.from_table(table, view), view,
                             LaneCameras.from_table(table, jit_array(mi.UInt32, owner)))
    ranges = view_ranges([len(c) if c is not None else 0 for c in parts])
    reading = SideReading(width, height, max_depth, hide_background, coverage)
    v, pixel, ok = curve_pass(scene, views, curve_table(curves), ranges, n_samples, sampler, reading)
    img = dr.zeros(mi.Float, width * height * 3 * count)
    for c in range(3):
        dr.scatter_reduce(dr.ReduceOp.Add, img, v[c], pixel * 3 + c, ok)
    return [img] if count == 1 else interior.split_views(img, count)


def curve_pass(scene, views: CurveCameras, curves: CurveTable, ranges, n_samples: int, sampler,
               reading: SideReading) -> tuple:
    """(v, pixel, mask) per lane of one pass over ``curves`` (:func:`curve_values`): the end points
    projected by ``views.projector``, weighed (:func:`curve_mass`) and drawn per lane among its
    view's (``ranges`` = (start, count) per view; :func:`draw_views` at :func:`stratified`
    uniforms: the sampler's first dimension). The traced pass and the recorded one
    (:mod:`psdr_cli.optimisation.frozen_batch`) both run this."""
    (q0, z0), (q1, z1) = views.projector.project(curves.p0), views.projector.project(curves.p1)
    mass = curve_mass(q0, q1, z0, z1, views.projector.near, curves.weight)
    start, count = ranges
    draw = draw_views(mass, start, count, views.view, stratified(sampler.next_1d(), n_samples, views.view), n_samples)
    return curve_values(scene, views, curves, (q0, q1), draw, sampler, reading)


def curve_values(scene, views: CurveCameras, table: CurveTable, ends, draw: Draw, sampler,
                 reading: SideReading) -> tuple:
    """(v, pixel, mask) per lane: the drawn curve point's contribution
    v = (1/N)·[(n_s·q(θ)) ΔL / p(q) − detach(·)] (AD, primal 0; :func:`curve_samples`) and its pixel
    in its view's part of the views' joined image (lane i's view ``views.view[i]``; None: one view)."""
    delta, pixel, n_s, q, ok = curve_samples(scene, views.cameras, table, ends, draw, sampler, reading)
    if views.view is not None:
        pixel += views.view * (reading.width * reading.height)
    v = delta * dr.dot(n_s, q)
    return v - dr.detach(v), pixel, ok


def curve_samples(scene, cameras, curves: CurveTable, ends, draw: Draw, sampler, reading: SideReading):
    """(ΔL / p(q) per lane, its pixel, screen normal n_s, film point q (AD), mask) of the points
    ``draw`` picks on ``curves`` (``ends`` = (q0, q1) their projected end points): the two sides'
    radiance (or coverage, :class:`SideReading`) difference at ±offset along n_s where the camera
    sees the curve point (see :func:`primary_boundary`)."""
    width, height = reading.width, reading.height
    k = draw.k
    qa, qb = gather_curve_points(ends[0], k), gather_curve_points(ends[1], k)
    q = qa + draw.s * (qb - qa)
    with dr.suspend_grad():
        qd = dr.detach(q)
        t = dr.normalize(dr.detach(qb - qa))
        n_s = mi.Vector2f(-t.y, t.x)
        ok = (qd.x >= 0) & (qd.x < width) & (qd.y >= 0) & (qd.y < height) & draw.alive
        eps = SIDE_EPS * max(width, height)
        own = [dr.gather(mi.UInt32, getattr(curves, a), k) for a in ("shape0", "face0", "shape1", "face1")]
        x0 = dr.gather(mi.Point3f, dr.detach(curves.p0), k)
        points = SidePoints(qd, n_s, x0, own)
        offsets = [mi.Float(-eps), mi.Float(eps)]
        if curves.crossings:  # intersection curves: clear the ray-spawn offset (see crossing_offsets)
            normals = [dr.gather(mi.Vector3f, getattr(curves, a), k) for a in ("normal0", "normal1")]
            offsets = crossing_offsets(scene, cameras, points, normals, max(width, height), ok)
        if curves.folds:  # mesh edges that fold back: clear the ray-spawn offset (see fold_offsets)
            normals = [dr.gather(mi.Vector3f, getattr(curves, a), k) for a in ("fold0", "fold1")]
            offsets = fold_offsets(scene, cameras, points, normals, max(width, height), offsets, ok)
        rays = [cameras(qd + o * n_s, ok) for o in offsets]
        strict = dr.gather(mi.Bool, curves.strict, k)
        inner = dr.gather(mi.Bool, curves.inner, k)
        # each side's first hit, traced once: for the visibility test and as the radiance's first vertex
        hits = [scene.ray_intersect(ray, ok) for ray in rays]
        ok &= edge_visible(scene, rays, (x0, dr.gather(mi.Point3f, dr.detach(curves.p1), k)), own, strict, inner, ok,
                           hits=hits)
        # common random numbers: both sides trace the same samples, so their difference keeps
        # the jump and loses most of the noise (each side alone stays unbiased)
        twin = sampler.clone()
        if reading.coverage is not None:  # the indicator of a first hit on the object: 1 on its side, 0 beyond it
            sides = [mi.Color3f(dr.select(ok & hits_shape(si, reading.coverage), 1.0, 0.0)) for si in hits]
        else:
            sides = [interior.radiance(scene, smp, ray, reading.max_depth, ok, hide_background=reading.hide_background,
                                       si=si) for smp, ray, si in zip((sampler, twin), rays, hits)]
        # 1/(N·p(q)) = Σw·ℓ / (N·w_e)
        inv_pdf = draw.scale / dr.gather(mi.Float, curves.weight, k)
        delta = dr.select(ok, (sides[0] - sides[1]) * inv_pdf, 0.0)
        pixel = dr.select(ok, film_pixel(qd, width), 0)
        dr.eval(delta, pixel, n_s, ok)
    return delta, pixel, n_s, q, ok


def estimate(scene, edges: BoundaryEdges, view: int, spp: int, seed: int, estimator, max_depth: int, *,
             guide=None) -> mi.Float:
    """One pass of the primary term (:class:`~.term.Term` signature), edges drawn by
    ``estimator.primary_sampling``."""
    n, sampler, P = boundary_pass(scene, edges, spp, seed)
    return primary_boundary(scene.mi_scene, scene.sensors[view], edges, P, n, sampler, max_depth,
                            sampling=estimator.primary_sampling, hide_background=scene.config.hide_background)


def estimate_views(scene, edges: BoundaryEdges, views, spp: int, seed: int, estimator, max_depth: int) -> list:
    """One pass of the primary term for several ``views`` traced as one wavefront (the samples of
    :func:`estimate`, drawn from one sampler seeded with ``seed``): a flat W·H·3 AD image per view."""
    n, sampler, P = boundary_pass(scene, edges, spp, seed, len(views))
    return views_primary_boundary(scene.mi_scene, [scene.sensors[v] for v in views], edges, P, n, sampler, max_depth,
                                  sampling=estimator.primary_sampling, hide_background=scene.config.hide_background)


TERM = Term("primary", samples_key="primary_spp", stream=2, estimate=estimate, estimate_views=estimate_views,
            reads_intersections=True)
