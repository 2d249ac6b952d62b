"""Boundary-segment sampling: a map u = (u1, u2) ∈ [0,1)³ → (x^B, ω) with its density.

The mathematics is docs/theory.md §2. u1 picks an edge ∝ its length and a uniform point x^B on
it, p(x^B) = 1/Σℓ per unit length; u2 picks ω by the ``dir`` technique (uniform over the
silhouette double wedge, p(ω) = 1/(4φ0), the uniform sphere on open edges) or the ``light``
technique (Mitsuba's emitter sampling from x^B, p(ω) in solid angle). A guide
(:mod:`psdr_cli.guiding`, §5) supplies u instead of independent uniforms and the sample is
divided by its density g(u); edge sorting (:mod:`psdr_cli.geometry.edge_sort`, §5) orders the edge list
into chains, traversing some edges backwards, so that x^B(u1) is continuous along each chain.

Parameters (experiment keys)
----------------------------
``estimator.edge_sort`` (bool, default false)
    Order the edges into chains (:func:`edge_list`).
``estimator.chains.max_turn`` (float in [0, 180] degrees, default 60)
    With edge sorting: a chain stops at a sharper turn.
``estimator.chains.max_length`` (int ≥ 1, default 1024)
    With edge sorting: most edges per chain.
``scene.objects[].edges`` (bool, default true)
    Only these objects' edges are boundary edges.
``scene.objects[].bsdf.type`` (BSDF name, default ``diffuse``)
    Objects with a transmissive BSDF (:data:`TRANSMISSIVE`) keep their concave edges (§2).

The technique (``estimator.sampling``) is chosen by the term that draws the samples
(:mod:`.direct`; :mod:`.indirect` always uses ``dir``).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import drjit as dr
import mitsuba as mi
import numpy as np

from ..geometry.edge_sort import Chains, sort_edges
from ..geometry.topology import build_topology, weld
from ..support.jitarray import jit_array

#: BSDFs through which a ray grazing a concave edge can continue (concave edges kept).
TRANSMISSIVE = ("dielectric", "roughdielectric", "thindielectric")


def normalize(v):
    return v / dr.norm(v)


def camera_origins(mi_scene: mi.Scene) -> np.ndarray:
    """(n, 3) positions of the scene's sensors (:func:`sensor_origins`): a closed mesh around one
    of them is a room, whose free space is its inside."""
    return sensor_origins(mi_scene.sensors())


def sensor_origins(sensors) -> np.ndarray:
    """(n, 3) positions of ``sensors`` (float64). Remembered for the Dr.Jit variables that hold
    them (a moved sensor holds new ones; the entry keeps them alive, so their indices are not
    reused meanwhile), so that an optimisation's iterations do not read each sensor's translation
    with a kernel of its own."""
    translations = [s.world_transform().translation() for s in sensors]
    key = tuple(t[c].index for t in translations for c in range(3))
    if 0 in key or key not in _ORIGINS:  # index 0: not a Dr.Jit variable, not remembered
        if len(_ORIGINS) >= 64:
            _ORIGINS.clear()
        _ORIGINS[key] = (translations, np.array([np.ravel(t) for t in translations], float).reshape(-1, 3))
    return _ORIGINS[key][1].copy()


#: sensor_origins per tuple of the sensors' translation variables: (those variables, origins)
_ORIGINS: dict = {}


@dataclass
class BoundaryEdges:
    """Secondary edges of every object with ``edges: true``.

    Vertex ids index the concatenation of those objects' ``vertex_positions`` buffers (in
    ``names`` order), so :meth:`positions` returns one differentiable buffer for all of them.
    ``ids``: v0, v1, v2 (face0 with normal n0) and v1, v0, v3 (face1 with normal n1, consistent
    with n0 whatever the faces' winding: see :mod:`psdr_cli.geometry.topology`; a copy of face0's on open
    edges); ``open``: border edges. ``meshes`` keeps (topology, vertex offset, smooth
    shading) per object for the per-view primary (silhouette) edges. ``flip``: edges traversed
    from v1 to v0 (edge sorting); ``chains``: the chain structure of the edge order (every edge
    its own chain unless sorted). ``segments``: the intersection segments of the last geometry
    they were searched for (:func:`psdr_cli.estimators.primary.scene_segments`), shared by the
    views of one iteration.
    """
    names: list
    ids: list
    open: mi.Bool
    count: int
    meshes: list = None
    flip: mi.Bool = None
    chains: object = None
    segments: dict = field(default_factory=dict)
    #: values computed once per vertex buffer (:meth:`remembered`)
    memo: dict = field(default_factory=dict)

    def remembered(self, name: str, arrays, make):
        """``make()``, computed once for the Dr.Jit variables ``arrays`` (by index; the entry holds
        them, so their indices cannot be reused meanwhile): the views of one iteration share the
        edge list and the vertex buffer, so what only depends on them is computed once."""
        key = tuple(a.index for a in arrays)
        hit = self.memo.get(name)
        if hit is not None and hit[0] == key and 0 not in key:
            return hit[2]
        value = make()
        self.memo[name] = (key, list(arrays), value)
        return value

    @staticmethod
    def from_scene(scene, sort: bool = False, max_turn: float = 60.0, max_length: int = 1024) -> "BoundaryEdges":
        """Secondary edges of the scene's edge objects, ordered into chains when ``sort`` (chains
        stop at turns sharper than ``max_turn`` degrees and at ``max_length`` edges)."""
        return BoundaryEdges.from_rows(edge_rows(scene.objects, camera_origins(scene.mi_scene), sort, max_turn,
                                                 max_length))

    @staticmethod
    def from_rows(rows: "EdgeRows") -> "BoundaryEdges":
        """The edge table ``rows`` as Dr.Jit arrays."""
        if not rows.names:
            return BoundaryEdges([], [], mi.Bool(), 0, [], mi.Bool(), Chains.unsorted(0))
        return BoundaryEdges(rows.names, [jit_array(mi.UInt32, c) for c in rows.cols], jit_array(mi.Bool, rows.open),
                             len(rows.open), rows.meshes, jit_array(mi.Bool, rows.chains.flip), rows.chains)

    def breakpoints(self, P) -> np.ndarray:
        """u1 values where chains start (and 1.0): x^B(u1) is continuous between two of them."""
        with dr.suspend_grad():
            p0 = dr.gather(mi.Point3f, P, self.ids[0])
            p1 = dr.gather(mi.Point3f, P, self.ids[1])
            length = np.asarray(dr.norm(p1 - p0), np.float64)
        cdf = np.concatenate([[0.0], np.cumsum(length)]) / max(length.sum(), 1e-30)
        return np.unique(np.r_[cdf[self.chains.starts], 1.0])

    def positions(self, params) -> mi.Float:
        """Flat (AD) buffer of the vertex positions of all edge objects (:func:`vertex_buffer`)."""
        return vertex_buffer(params, self.names)


def vertex_buffer(params, names) -> mi.Float:
    """The vertex positions of the objects ``names`` end to end, flat (AD), from their parameters."""
    bufs = [params[f"{n}.vertex_positions"] for n in names]
    return bufs[0] if len(bufs) == 1 else dr.concat(bufs)


@dataclass
class EdgeRows:
    """The edge table of :class:`BoundaryEdges` in numpy (:func:`edge_rows`): its six vertex-id
    columns (uint32), open flags, ``meshes`` (topology, vertex offset, smooth shading) and chains."""
    names: list
    cols: list
    open: np.ndarray
    meshes: list
    chains: Chains


def edge_rows(objects: dict, cameras: np.ndarray, sort: bool = False, max_turn: float = 60.0,
              max_length: int = 1024) -> EdgeRows:
    """Secondary edges of the objects with ``edges: true`` among ``objects`` (name → scene object
    with numpy ``vertices``, ``faces`` and its ``config``), ``cameras`` the sensors' positions
    (:func:`camera_origins`), in chains when ``sort``. numpy only: it may run on a thread of its own
    while Dr.Jit kernels run (:mod:`psdr_cli.optimisation.geometry_ahead`)."""
    cols = [[] for _ in range(6)]
    opens, names, meshes, verts, offset = [], [], [], [], 0
    for name, om in objects.items():
        if not om.edges:
            continue
        topo = build_topology(om.vertices, om.faces, viewpoints=cameras)
        meshes.append((topo, offset, bool(om.config.smooth)))
        sel = topo.secondary(transmissive=om.config.bsdf.type in TRANSMISSIVE)
        o = topo.open[sel]
        face1 = (np.where(o, topo.v0[sel], topo.v1[sel]), np.where(o, topo.v1[sel], topo.v0[sel]),
                 np.where(o, topo.v2[sel], topo.v3[sel]))
        for c, arr in zip(cols, (topo.v0[sel], topo.v1[sel], topo.v2[sel], *face1)):
            c.append(arr + offset)
        opens.append(topo.open[sel])
        names.append(name)
        verts.append(np.asarray(om.vertices, float))
        offset += len(om.vertices)
    if not names:
        return EdgeRows([], [], np.zeros(0, bool), [], Chains.unsorted(0))
    cols = [np.concatenate(c).astype(np.uint32) for c in cols]
    opens = np.concatenate(opens)
    chains = Chains.unsorted(len(opens))
    if sort and len(opens):
        wid, rep = weld(np.concatenate(verts))
        V = np.concatenate(verts)[rep]
        chains = sort_edges(V, wid[cols[0]], wid[cols[1]], max_turn, max_length)
        cols = [c[chains.order] for c in cols]
        opens = opens[chains.order]
    return EdgeRows(names, cols, opens, meshes, chains)


def edge_list(scene, estimator, sort: bool) -> BoundaryEdges:
    """The scene's boundary edges, ordered into chains when ``sort`` with the estimator
    configuration's chain parameters (``estimator.chains``)."""
    return BoundaryEdges.from_scene(scene, sort, estimator.chains.max_turn, estimator.chains.max_length)


@dataclass
class EdgeSample:
    """A point x^B on a sampled edge with the edge's local geometry (all detached but ``xB``)."""
    xB: mi.Point3f       # AD: moves with the vertex positions
    p0: mi.Point3f
    p2: mi.Point3f
    e: mi.Vector3f       # unit edge direction
    n0: mi.Vector3f
    n1: mi.Vector3f
    open: mi.Bool
    pdf: mi.Float        # p(x^B) per unit length


def primary_sample(sampler: mi.Sampler, guide=None):
    """(u1, u2, g(u)): independent uniforms, or a draw from ``guide`` with its density g."""
    u1, u2 = sampler.next_1d(), sampler.next_2d()
    if guide is None:
        return u1, u2, mi.Float(1.0)
    u, g = guide.sample(sampler.next_1d(), mi.Point3f(u1, u2.x, u2.y))
    return u.x, mi.Point2f(u.y, u.z), g


#: Bisection steps of :meth:`LengthDistribution.sample_reuse`: enough for 2^24 edges.
SEARCH_STEPS = 24


class LengthDistribution:
    """Edges drawn ∝ their length ℓ_k: inclusive cumulative sums C_k = Σ_{i≤k} ℓ_i, total
    T = C_{n−1}. ``sample_reuse(u)`` takes the first k with C_k > u·T (among edges of positive
    length) and reuses the remainder s = (u·T − C_{k−1}) / ℓ_k ∈ [0, 1), as Mitsuba's
    ``DiscreteDistribution.sample_reuse``; ``sum()`` is T. The count n enters as an array and the
    bisection takes :data:`SEARCH_STEPS` steps whatever n is, so no kernel depends on the number
    of edges (a frozen function replays it for any count, :mod:`psdr_cli.optimisation.frozen_batch`)."""

    def __init__(self, lengths: mi.Float, count: mi.UInt32):
        self.pmf = lengths
        self.cdf = dr.cumsum(lengths)  # inclusive
        self.count = count
        self.total = dr.gather(mi.Float, self.cdf, count - 1)
        index = dr.arange(mi.UInt32, dr.width(lengths))
        self.last = dr.max(dr.select(lengths > 0, index, 0))  # the last edge of positive length
        dr.eval(self.cdf, self.total, self.last)

    def sum(self) -> mi.Float:
        return self.total

    def sample_reuse(self, u: mi.Float):
        x = u * self.total
        lo, size = dr.zeros(mi.UInt32, dr.width(u)), dr.gather(mi.UInt32, self.count, dr.zeros(mi.UInt32, dr.width(u)))
        for _ in range(SEARCH_STEPS):  # first k in [lo, lo + size) with C_k > x
            half = size >> 1
            right = (size > 0) & (dr.gather(mi.Float, self.cdf, lo + half, size > 0) <= x)
            lo = dr.select(right, lo + half + 1, lo)
            size = dr.select(right, size - half - 1, half)
        k = dr.minimum(lo, dr.gather(mi.UInt32, self.last, dr.zeros(mi.UInt32, dr.width(u))))
        pmf = dr.gather(mi.Float, self.pmf, k)
        s = (x - (dr.gather(mi.Float, self.cdf, k) - pmf)) / dr.select(pmf > 0, pmf, 1.0)
        return k, dr.clip(s, 0.0, dr.one_minus_epsilon(mi.Float))


def length_distribution(edges: BoundaryEdges, P, count: mi.UInt32 | None = None) -> LengthDistribution:
    """:class:`LengthDistribution` of the edges' current (detached) lengths; ``count``: the number
    of edges as an array (default: ``edges.count``)."""
    if count is None and edges.count >= 1 << SEARCH_STEPS:
        raise ValueError(f"{edges.count} boundary edges: the edge draw serves fewer than 2^{SEARCH_STEPS}")
    with dr.suspend_grad():
        p0 = dr.gather(mi.Point3f, P, edges.ids[0])
        p1 = dr.gather(mi.Point3f, P, edges.ids[1])
        # opaque: a count written into the kernels as a constant would compile them anew for every count
        return LengthDistribution(dr.norm(p1 - p0), dr.opaque(mi.UInt32, edges.count) if count is None else count)


def edge_distribution(edges: BoundaryEdges, P) -> LengthDistribution:
    """Edge-selection distribution ∝ current (detached) edge lengths (built once per vertex
    buffer ``P``: every view of an iteration samples the same one)."""
    return edges.remembered("distribution", [P], lambda: length_distribution(edges, P))


@dataclass
class EdgeDraw:
    """The boundary edges of a pass as its samples draw them: the ``edges``, the vertex buffer
    ``P`` their end points index (AD when the vertices move) and the distribution ``distr`` an
    edge is drawn from (:func:`edge_distribution`, or one built for a recorded pass)."""
    edges: BoundaryEdges
    P: object
    distr: object


def edge_draw(edges: BoundaryEdges, P) -> EdgeDraw:
    """The edges at positions ``P``, drawn ∝ their length (:func:`edge_distribution`)."""
    return EdgeDraw(edges, P, edge_distribution(edges, P))


def sample_edge_point(edges: BoundaryEdges, P, distr: LengthDistribution, u1: mi.Float) -> EdgeSample:
    """x^B = p0 + s (p1 − p0) for the edge k chosen by u1 (s reuses the remainder of u1, or is
    1 − remainder on flipped edges)."""
    k, s = distr.sample_reuse(u1)
    s = dr.select(dr.gather(mi.Bool, edges.flip, k), 1.0 - s, s)
    vid = [dr.gather(mi.UInt32, a, k) for a in edges.ids]
    p0, p1 = dr.gather(mi.Point3f, P, vid[0]), dr.gather(mi.Point3f, P, vid[1])
    xB = p0 + s * (p1 - p0)
    with dr.suspend_grad():
        q = [dr.detach(dr.gather(mi.Point3f, P, v)) for v in vid]
        n0 = normalize(dr.cross(q[1] - q[0], q[2] - q[0]))
        n1 = normalize(dr.cross(q[4] - q[3], q[5] - q[3]))
        return EdgeSample(xB=xB, p0=q[0], p2=q[2], e=normalize(q[1] - q[0]), n0=n0, n1=n1,
                          open=dr.gather(mi.Bool, edges.open, k), pdf=dr.rcp(distr.sum()))


def wedge_angle(n0, n1):
    """φ0 = acos(n0·n1), the opening angle of the silhouette wedge."""
    return dr.acos(dr.clip(dr.dot(n0, n1), -1.0, 1.0))


def sample_wedge(edge: EdgeSample, u: mi.Point2f):
    """``dir`` technique: ω uniform over the double wedge (uniform sphere on open edges).

    With Z = normalize(n0 + n1), Y = normalize(n0 × Z), X = Y × Z and φ = (u_a − ½)φ0:
    X1 = X cosφ + Z sinφ, b = 4u_b − 1 (u_b ≤ ½) or 4u_b − 3, ω = ±√(1 − b²) X1 + b Y.
    """
    phi0 = wedge_angle(edge.n0, edge.n1)
    Z = normalize(edge.n0 + edge.n1)
    Y = normalize(dr.cross(edge.n0, Z))
    X = dr.cross(Y, Z)
    phi = (u.x - 0.5) * phi0
    X1 = X * dr.cos(phi) + Z * dr.sin(phi)
    lo = u.y <= 0.5
    b = dr.select(lo, 4.0 * u.y - 1.0, 4.0 * u.y - 3.0)
    a = dr.select(lo, 1.0, -1.0) * dr.safe_sqrt(1.0 - b * b)
    w = a * X1 + b * Y
    w = dr.select(edge.open, mi.warp.square_to_uniform_sphere(u), w)
    return w, pdf_wedge(edge)


def pdf_wedge(edge: EdgeSample):
    """p(ω) of the ``dir`` technique: 1/(4φ0), or 1/(4π) on open edges."""
    return dr.select(edge.open, dr.inv_four_pi, dr.rcp(4.0 * wedge_angle(edge.n0, edge.n1)))


def in_wedge(edge: EdgeSample, w, eps: float = 1e-6):
    """Whether ω lies strictly inside the silhouette wedge (open edges: off the face plane)."""
    c0, c1 = dr.dot(edge.n0, w), dr.dot(edge.n1, w)
    closed_ok = (c0 * c1 < 0) & (dr.abs(c0) > eps) & (dr.abs(c1) > eps)
    return dr.select(edge.open, dr.abs(c0) > eps, closed_ok)


def ray_origin(edge: EdgeSample, rel_eps: float = 1e-5):
    """Start of both segment rays: x^B pushed off the edge.

    Closed edges: along the outward bisector Z = normalize(n0 + n1); every line with ω inside the
    wedge then misses both faces by ≥ ε cos(φ0/2) (offsetting along ±ω instead re-hits a face near
    the wedge border and biases the estimate). Open edges: in the face plane, away from the face.
    """
    xB = dr.detach(edge.xB)
    eps = rel_eps * (1.0 + dr.max(dr.abs(xB)))
    out = normalize(dr.cross(edge.e, edge.n0))
    out = dr.select(dr.dot(out, edge.p2 - edge.p0) > 0, -out, out)
    offset = dr.select(edge.open, out, normalize(edge.n0 + edge.n1))
    return xB + eps * offset
