"""Owns the part of an optimisation iteration that Dr.Jit records once and replays
(``dr.freeze``). Reads the problem's scene, the cameras, the targets and the iteration's edges and
curves; writes the gradients of the scene's leaf buffers.

For the mini-batch of views v₁…v_B it records the adjoint render P (``optimize.adjoint_spp``
samples per pixel; without one, the interior render's own primal), the loss ℓ and its adjoint
δ = ∂ℓ/∂I, summed over the losses of :mod:`.losses.registry` that apply to the run, each in its
recorded form (:class:`.losses.loss.RecordedLoss`; the L1 loss's

    ℓ = Σ |P − T| / (3·W·H·B),    δ = sign(P − T) / (3·W·H·B)   (0 where P = T without an adjoint render),

the derivative the traced loop takes of ``losses.l1.l1_loss``: Dr.Jit's derivative of |x| is 0
at x = 0), and the interior term's reverse pass, the backward of Σ δ·I_interior into the scene's
leaf buffers (:meth:`psdr_cli.problem.Problem.apply_leaves`): the traced loop's derivative of its
loss, split by term (a run with a loss that has no recorded form is traced: :func:`refusal`).
Once the iteration's edge table is there, two boundary terms' backward passes are recorded and
replayed too: the direct term's Σ δ·I_direct (unguided; the edges enter as arrays padded to a
power of two, :func:`padded_edges`, and are drawn ∝ length by
:class:`.estimators.boundary_sampling.LengthDistribution`, whose kernels do not depend on their
number) and the primary term's Σ δ·I_primary (each view's curves selected on the host in numpy,
:func:`.estimators.primary.primary_edge_ids`, and handed over end to end as arrays padded to a
power of two, :func:`packed_curves`; projected, weighed and drawn on the device,
:func:`.estimators.primary.draw_views`; an iteration with intersection curves traces the term).
The loop adds the other terms' Σ δ·I_term traced, and one backward pass through the large-steps
solve carries the leaves' gradient to the optimiser.

Everything that varies between iterations enters as data: the batch as an array of view indices
into the run's cameras (:class:`.estimators.camera.CameraTable`), the seeds as arrays, the targets
of all views as one array, the edges and curves as padded arrays with their counts. A recording
is replayed only while the structure it was recorded on holds (:class:`BatchShape`,
:class:`DirectShape`, :class:`PrimaryShape`: the scene object, the film, the batch size, the
sample counts and passes, the losses, the slots); when it changes (a remesh builds a new scene, a
stage a new film) the next call is traced and recorded again. Guided passes, which read their
guides' numpy between kernels, stay traced.

Parameters (experiment keys)
----------------------------
``optimize.freeze`` (bool, default true)
    Record and replay this part when the run allows it (:func:`refusal` says when it does not);
    false: every iteration is traced (the same estimator; the cameras from Mitsuba's
    sensor objects instead of the table, equal up to rounding).
"""
from __future__ import annotations

import gc
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from .estimate import has_guide, term_passes
from .estimators.boundary_sampling import (SEARCH_STEPS, BoundaryEdges, length_distribution, sensor_origins,
                                           vertex_buffer)
from .estimators.camera import CameraTable, LaneCameras, ViewLanes, is_perspective, table_camera_rays
from .estimators.direct import direct_samples
from .estimators.interior import radiance
from .estimators.primary import (CurveCameras, CurveTable, SideReading, camera_edge_ids, crossing_count, curve_pass,
                                 drawable, edge_shape_ids, view_starts)
from .estimators.passes import AD_LANES, make_sampler, passes_for, views_seed
from .estimators.registry import ADJOINT_STREAM, RENDER_STREAM
from .estimators.registry import term as registry_term
from .jitarray import jit_array
from .losses.registry import recorded_names, recorded_sum, recording_refusal

#: The term whose reverse pass is recorded with the adjoint render (before the edge table is there).
FROZEN_TERM = "interior"
#: The boundary term whose reverse pass is recorded once the edge table is there.
DIRECT_TERM = "direct"
#: The term whose reverse pass is recorded once the iteration's curves are selected (host side).
PRIMARY_TERM = "primary"
#: Most edges the direct part's draw serves (boundary_sampling.SEARCH_STEPS bisection steps).
MAX_EDGES = 1 << SEARCH_STEPS
#: Fewest edge slots of the direct part (:func:`padded_edges`).
MIN_EDGE_SLOTS = 256


@dataclass(frozen=True)
class BatchShape:
    """What a recording is valid for: the scene object (a remesh builds a new one), the film
    W × H, the batch size B, the interior term's samples per pixel, the adjoint render's passes,
    the path depth, whether camera rays that leave the scene see the background, and the names of
    the losses that apply to the run, whose recorded forms it sums."""
    scene_id: int
    width: int
    height: int
    views: int
    spp: int
    adjoint_passes: tuple
    max_depth: int
    hide_background: bool
    losses: tuple


@dataclass(frozen=True)
class DirectShape:
    """What a recording of the direct term's part is valid for: the scene object, the film, the
    batch size, the term's samples per pixel, its sampling technique and the objects whose edges
    are drawn (their vertex buffers, in order)."""
    scene_id: int
    width: int
    height: int
    views: int
    spp: int
    sampling: str
    names: tuple
    slots: int


@dataclass(frozen=True)
class PrimaryShape:
    """What a recording of the primary term's part is valid for: the scene object, the film, the
    batch size, the term's samples per pixel, the curve slots, the objects whose edges are curves,
    the path depth, whether camera rays that leave the scene see the background, and whether some
    curve folds back (:func:`.estimators.primary.fold_offsets` traced or not)."""
    scene_id: int
    width: int
    height: int
    views: int
    spp: int
    slots: int
    names: tuple
    max_depth: int
    hide_background: bool
    folds: bool


def edge_slots(count: int) -> int:
    """The edge arrays' length in the direct part: ``count`` rounded up to a power of two (at
    least :data:`MIN_EDGE_SLOTS`), so that one recording serves every count up to it with inputs
    of one length (the case tests/test_frozen_batch.py replays; :meth:`FrozenBatch.direct` keeps
    the largest a scene needed)."""
    return max(MIN_EDGE_SLOTS, 1 << (count - 1).bit_length())


def padded_edges(edges: BoundaryEdges, slots: int) -> tuple:
    """(ids, flip, open) of ``edges`` padded to ``slots`` entries with edges of length 0 (both
    ends vertex 0: never drawn, :class:`.estimators.boundary_sampling.LengthDistribution`)."""
    index = dr.arange(mi.UInt32, slots)
    count = opaque(edges.count)  # (a constant would compile this kernel anew for every count)
    real = index < count
    at = dr.minimum(index, count - 1)
    ids = [dr.select(real, dr.gather(mi.UInt32, a, at), 0) for a in edges.ids]
    flip = real & dr.gather(mi.Bool, edges.flip, at)
    open_ = real & dr.gather(mi.Bool, edges.open, at)
    dr.eval(ids, flip, open_)
    return ids, flip, open_


def refusal(problem, stage, cfg, engine, settings, batch: int) -> str | None:
    """Why the frozen part cannot serve this run (None: it can). It needs psdr's interior term
    with a batch of ``batch`` views in one AD pass, for every loss that applies to the run a
    recorded form that stands for it on ``stage`` (:func:`.losses.registry.recording_refusal`: the
    L1 loss's takes no pixel weights, the silhouette loss of masked views has none), the shape as
    the only unknown (its vertex buffer written by the large-steps solve: Dr.Jit 1.5 replays a
    buffer written from the host wrongly, docs/benchmarks/iteration_time.md, "The recorded part of
    an iteration") and Mitsuba's perspective cameras, fixed."""
    if not cfg.freeze:
        return "optimize.freeze is false"
    if engine.name != "psdr" or FROZEN_TERM not in engine.terms:
        return "the interior term is not psdr's"
    losses = recording_refusal(stage, cfg)
    if losses is not None:
        return losses
    if list(problem.opt.keys()) != ["u"]:
        return "unknowns besides the shape (albedo, lighting, materials)"
    if problem.cameras is not None and (problem.cameras.attached or problem.cameras.moved):
        return "camera poses refined (the recorded batch holds the starting cameras as constants)"
    if not all(is_perspective(s) for s in problem.scene.sensors):
        return "a camera other than Mitsuba's perspective camera"
    width, height = problem.scene.resolution
    if batch * width * height * term_passes(FROZEN_TERM, settings, width * height)[0] > AD_LANES:
        return "the batch's interior pass is wider than one AD pass"
    return None


def batch_loss(shape: BatchShape, mi_scene, table: CameraTable, targets: mi.Float, views: mi.UInt32,
               interior_seed: mi.UInt32, adjoint_seeds: list):
    """(ℓ, δ) of the module docstring, the interior term's backward pass run here. ``targets``
    holds every view's target (flat W·H·3 each, view-major), ``views`` the batch's indices into it
    and into ``table``; ``adjoint_seeds`` one seed per pass of ``shape.adjoint_passes``. Without
    adjoint passes P is the interior render's own primal (the losses' derivatives are then those
    the traced loss takes of I itself, :class:`.losses.loss.RecordedLoss`)."""
    n = 3 * shape.width * shape.height
    image = pass_sums(shape, mi_scene, table, views, shape.spp, interior_seed, ad=True) / shape.spp
    with dr.suspend_grad():
        if shape.adjoint_passes:
            P = None
            for spp, seed in zip(shape.adjoint_passes, adjoint_seeds):
                sums = pass_sums(shape, mi_scene, table, views, spp, seed, ad=False)
                P = sums if P is None else P + sums
            P = P / sum(shape.adjoint_passes)
        else:
            P = dr.detach(image)
        lane = dr.arange(mi.UInt32, n * shape.views)
        k = lane // n  # (literals here and below: recorded per structure; an opaque scalar is a memset per replay)
        T = dr.gather(mi.Float, targets, dr.gather(mi.UInt32, views, k) * n + (lane - k * n))
        loss, delta = recorded_sum(shape.losses, P, T, primal=not shape.adjoint_passes)
    dr.backward(dr.sum(delta * image))
    return loss, delta


def pass_sums(shape: BatchShape, mi_scene, table: CameraTable, views: mi.UInt32, spp: int, seed: mi.UInt32,
              ad: bool) -> mi.Float:
    """One pass of the batch's views in one wavefront: the sum over ``spp`` samples of every pixel,
    flat (B · H · W · 3), view-major (the samples of :func:`.estimators.interior.views_pass` and
    of the interior term's ``estimate_views`` with the cameras as data)."""
    sampler = make_sampler(seed, shape.width * shape.height * spp * shape.views)
    ray = table_camera_rays(table, views, sampler, spp)
    L = radiance(mi_scene, sampler, ray, shape.max_depth, ad=ad, hide_background=shape.hide_background)
    dr.eval(L)  # one kernel for the three channels
    return dr.ravel(mi.Color3f([dr.block_sum(L[c], spp, mode="evaluated") for c in range(3)]))


def direct_backward(shape: DirectShape, mi_scene, table: CameraTable, views: mi.UInt32, seed: mi.UInt32,
                    padded: tuple, delta: mi.Float):
    """The direct term's pass over the batch (the samples of its ``estimate_views``, the cameras
    from ``table``) and the backward pass of Σ δ·I_direct into the scene's leaves. The edges
    ``padded`` = (ids: their six vertex-id columns, flip, open, count; ``shape.slots`` entries, of
    which ``count`` real ones, at least one, and the rest of length 0: :func:`padded_edges`) index
    the concatenated vertex buffers of ``shape.names``."""
    ids, flip, open_, count = padded
    edges = BoundaryEdges(list(shape.names), ids, open_, shape.slots, flip=flip)  # (the real count: ``count``)
    P = edges.positions(mi.traverse(mi_scene))
    n = shape.spp * shape.width * shape.height
    sampler = make_sampler(seed, n * shape.views)
    k = dr.arange(mi.UInt32, n * shape.views) // n
    lanes = ViewLanes(LaneCameras.from_table(table, dr.gather(mi.UInt32, views, k)), k, shape.views)
    samples = direct_samples(mi_scene, lanes, edges, P, n, sampler, shape.sampling,
                             distr=length_distribution(edges, P, count))
    dr.backward(adjoint_sum(delta, samples))
    return count  # (a frozen function returns something)


def primary_backward(shape: PrimaryShape, mi_scene, table: CameraTable, views: mi.UInt32, seed: mi.UInt32,
                     packed: mi.UInt32, delta: mi.Float):
    """The primary term's pass over the batch (the samples of its ``estimate_views``: the draw,
    the side rays and radiances; the cameras from ``table``) and the backward pass of
    Σ δ·I_primary into the scene's leaves. ``packed`` holds the batch's curves end to end
    (:func:`packed_curves`: ``shape.slots`` entries, view j's the ``count[j]`` from ``start[j]``,
    the rest of weight 0), their end points vertex ids into the concatenated vertex buffers of
    ``shape.names``; each curve is projected into its own view's camera."""
    columns, start, count = unpacked_curves(packed, shape.slots, shape.views)
    P = vertex_buffer(mi.traverse(mi_scene), shape.names)
    none = dr.zeros(mi.Vector3f, shape.slots)  # no intersection curves (refused before)
    curves = CurveTable(dr.gather(mi.Point3f, P, columns["v0"]), dr.gather(mi.Point3f, P, columns["v1"]),
                        columns["shape"], columns["face0"], columns["shape"], columns["face1"], columns["strict"],
                        columns["inner"], columns["weight"], none, none, columns["fold0"], columns["fold1"], False,
                        shape.folds)
    n = shape.spp * shape.width * shape.height
    sampler = make_sampler(seed, n * shape.views)
    view = dr.arange(mi.UInt32, n * shape.views) // n
    cameras = CurveCameras(LaneCameras.from_table(table, dr.gather(mi.UInt32, views, view)), view,
                           LaneCameras.from_table(table, dr.gather(mi.UInt32, views, columns["view"])))
    reading = SideReading(shape.width, shape.height, shape.max_depth, shape.hide_background)
    samples = curve_pass(mi_scene, cameras, curves, (start, count), n, sampler, reading)
    dr.backward(adjoint_sum(delta, [samples]))
    return count


#: The primary part's curve columns in their packed order (:func:`packed_curves`): name, number
#: of components, type.
CURVE_COLUMNS = (("v0", 1, "u"), ("v1", 1, "u"), ("face0", 1, "u"), ("face1", 1, "u"), ("shape", 1, "u"),
                 ("strict", 1, "b"), ("inner", 1, "b"), ("weight", 1, "f"), ("fold0", 3, "f"), ("fold1", 3, "f"),
                 ("view", 1, "u"))


def packed_curves(parts, ids: np.ndarray, slots: int) -> tuple:
    """(packed, folds): the primary curves ``parts`` of the batch's views (each
    :func:`.estimators.primary.camera_edge_ids`), end to end and padded to ``slots`` entries of
    weight 0, as one UInt32 array: each component of :data:`CURVE_COLUMNS` in turn (end-point
    vertex ids v0, v1, the two face indices, the edge object's registry id (``ids`` per object),
    strict, inner, the weight w_e and the fold normals as float bits, the curve's view, its
    position in the batch), then each view's first curve and count; and whether some curve
    folds back. One upload, freed as one (an array mapped from numpy is released by a host
    function after the kernels that read it: one operation per array)."""
    counts = drawable([len(p["v0"]) for p in parts])
    values = {name: np.concatenate([p[name] for p in parts]) for name in parts[0]}
    values["shape"] = ids[values["mesh"]]
    values["view"] = np.repeat(np.arange(len(parts)), counts)
    total = int(counts.sum())
    blocks = []
    for name, width, kind in CURVE_COLUMNS:
        a = np.asarray(values[name]).reshape(total, width)
        a = np.concatenate([a, np.zeros((slots - total, width), a.dtype)])
        a = a.astype(np.float32).view(np.uint32) if kind == "f" else a.astype(np.uint32)
        blocks.extend(a[:, c] for c in range(width))
    blocks += [view_starts(counts).astype(np.uint32), counts.astype(np.uint32)]
    return jit_array(mi.UInt32, np.concatenate(blocks)), bool(np.any(values["fold0"]))


def unpacked_curves(packed: mi.UInt32, slots: int, views: int) -> tuple:
    """(columns by name, start, count): the arrays :func:`packed_curves` packed."""
    index = dr.arange(mi.UInt32, slots)
    columns, offset = {}, 0
    for name, width, kind in CURVE_COLUMNS:
        parts = [dr.gather(mi.UInt32, packed, index + offset + c * slots) for c in range(width)]
        offset += width * slots
        if kind == "f":
            parts = [dr.reinterpret_array(mi.Float, x) for x in parts]
        columns[name] = parts[0] != 0 if kind == "b" else parts[0] if width == 1 else mi.Vector3f(*parts)
    view = dr.arange(mi.UInt32, views)
    start, count = dr.gather(mi.UInt32, packed, view + offset), dr.gather(mi.UInt32, packed, view + offset + views)
    dr.eval(columns, start, count)  # one kernel (left lazy, the later kernels would gather them again per use)
    return columns, start, count


def adjoint_sum(delta: mi.Float, samples) -> mi.Float:
    """Σ δ·I of the image I that the lanes' contributions ``samples`` ((v, pixel, mask) each, v a
    colour, the pixel's index in the views' joined image) add up to, without forming I:
    Σ_lanes Σ_c δ[3·pixel + c]·v_c. Its reverse pass gives each lane δ at its pixel, as the
    scattered image's would (no image to zero, no scatter)."""
    total = mi.Float(0.0)
    for v, pixel, ok in samples:
        for c in range(3):
            total += dr.select(ok, dr.gather(mi.Float, delta, pixel * 3 + c, ok) * v[c], 0.0)
    return dr.sum(total)


class Recording:
    """``dr.freeze(body)`` bound to one structure (``shape``) per function; the functions of one
    scene are kept (a structure that comes back, such as curves that fold back or not, replays),
    a new scene drops them. ``enabled`` false calls the body traced (the fallback).

    A Ctrl-C at any moment of a call reaches the caller as KeyboardInterrupt (Dr.Jit reports one
    that stops a recording as a RuntimeError caused by one, through up to four layers of its own
    errors), and the function is recorded afresh at its next call. Python's cyclic garbage
    collector does not run during a call: a collection while Dr.Jit records may free an array
    mapped from numpy whose release is a host function, which a recording cannot hold, and Dr.Jit
    then aborts the process (seen after interrupted recordings, whose tracebacks leave such
    cycles)."""

    def __init__(self, body, enabled: bool = True):
        self.body, self.enabled = body, enabled
        self.scene_id, self.fns = None, {}
        self.earlier = 0  # recordings of earlier scenes' functions

    def reset(self):
        """Drop the functions (a new scene or stage)."""
        self.earlier = self.n_recordings
        self.scene_id, self.fns = None, {}

    def __call__(self, shape, *args):
        if shape.scene_id != self.scene_id:
            self.reset()
            self.scene_id = shape.scene_id
        if shape not in self.fns:
            bound = _bind(self.body, shape)
            self.fns[shape] = dr.freeze(bound, warn_after=1000) if self.enabled else bound
        collecting = gc.isenabled()
        try:
            gc.disable()
            return self.fns[shape](*args)
        except BaseException as error:
            self.fns.pop(shape, None)  # a recording cut short is not replayed
            interrupt = interrupt_in(error)
            if interrupt is not None and interrupt is not error:  # Dr.Jit wraps what stopped a recording
                raise KeyboardInterrupt() from None
            raise
        finally:
            if collecting:
                gc.enable()

    @property
    def n_recordings(self) -> int:
        if not self.enabled:
            return 0
        return self.earlier + sum(fn.n_recordings for fn in self.fns.values())


class FrozenBatch:
    """The recorded parts of a run's iterations (module docstring). ``enabled`` false runs the same
    functions traced every call (the fallback, and the reference the tests compare with)."""

    def __init__(self, enabled: bool = True):
        self.enabled = enabled
        self.interior = Recording(batch_loss, enabled)
        self.direct_part = Recording(direct_backward, enabled)
        self.primary_part = Recording(primary_backward, enabled)
        self.scene_id = self.stage = self.scene = None
        self.slots = 0  # the edge slots of the direct part: the most this scene needed
        self.curve_slots = 0  # the curve slots of the primary part: the most this scene needed
        self.origins = None
        self.table = self.targets = None

    def structure(self, problem, stage, views, settings, cfg) -> BatchShape:
        width, height = problem.scene.resolution
        spp = term_passes(FROZEN_TERM, settings, width * height)[0]  # one pass per iteration, as ad_images
        adjoint = tuple(passes_for(cfg.adjoint_spp, width * height * len(views))) if cfg.adjoint_spp else ()
        return BatchShape(id(problem.scene.mi_scene), width, height, len(views), spp, adjoint,
                          settings.max_depth, bool(problem.scene.config.hide_background),
                          recorded_names(stage, cfg))

    def prepare(self, problem, stage):
        """The cameras and the targets of a new scene or stage as arrays."""
        width, height = problem.scene.resolution
        self.scene_id, self.stage = id(problem.scene.mi_scene), stage
        self.scene = problem.scene.mi_scene  # held: its id cannot name another scene meanwhile
        self.slots = self.curve_slots = 0
        self.table = CameraTable.of(problem.scene.sensors, width, height)
        self.origins = sensor_origins(problem.scene.sensors)
        for part in (self.interior, self.direct_part, self.primary_part):
            part.reset()  # (a recording keyed by a scene's id must not outlive it: ids are reused)
        self.targets = jit_array(mi.Float, np.concatenate([np.ravel(np.asarray(a, np.float32))
                                                             for a in stage.arrays]))

    def __call__(self, problem, stage, views, iteration: int, settings, cfg):
        """(ℓ, δ) of iteration ``iteration``'s batch ``views`` on the current scene (whose
        unknowns are leaves: the interior term's gradient is accumulated into them)."""
        shape = self.structure(problem, stage, views, settings, cfg)
        if shape.scene_id != self.scene_id or stage is not self.stage:
            self.prepare(problem, stage)
        interior = views_seed(settings.seed, views, iteration, registry_term(FROZEN_TERM).stream)
        adjoint = views_seed(settings.seed, views, iteration, ADJOINT_STREAM)
        seeds = [opaque(views_seed(adjoint, views, p, RENDER_STREAM)) for p in range(len(shape.adjoint_passes))]
        return self.interior(shape, problem.scene.mi_scene, self.table, self.targets, mi.UInt32(views),
                             opaque(interior), seeds)

    def serves_direct(self, problem, views, settings, edges, guides) -> bool:
        """Whether the direct term's part can run on this iteration's ``edges`` (unguided, the
        batch in one AD pass, 1 to :data:`MAX_EDGES` edges)."""
        width, height = problem.scene.resolution
        spp = term_passes(DIRECT_TERM, settings, width * height)[0]
        return edges is not None and 0 < edges.count < MAX_EDGES and not has_guide(guides, DIRECT_TERM) and \
            len(views) * width * height * spp <= AD_LANES

    def direct(self, problem, views, iteration: int, settings, edges, delta: mi.Float):
        """The direct term's backward pass of Σ δ·I_direct over the batch ``views`` (into the
        scene's leaves), replayed; :meth:`__call__` must have run for this scene."""
        if id(problem.scene.mi_scene) != self.scene_id:
            raise RuntimeError("FrozenBatch.direct: the batch's part must run first for this scene")
        width, height = problem.scene.resolution
        self.slots = max(self.slots, edge_slots(edges.count))  # never fewer: a count going back and
        # forth across a power of two would record again each time
        shape = DirectShape(id(problem.scene.mi_scene), width, height, len(views),
                            term_passes(DIRECT_TERM, settings, width * height)[0], settings.estimator.sampling,
                            tuple(edges.names), self.slots)
        seed = views_seed(settings.seed, views, iteration, registry_term(DIRECT_TERM).stream)
        ids, flip, open_ = padded_edges(edges, shape.slots)
        self.direct_part(shape, problem.scene.mi_scene, self.table, mi.UInt32(views), opaque(seed),
                         (ids, flip, open_, opaque(edges.count)), delta)

    def serves_primary(self, problem, views, settings, edges) -> bool:
        """Whether the primary term's part can run on this iteration's ``edges`` (the batch in one
        AD pass, edge objects with meshes, no intersection curve: those stay traced)."""
        width, height = problem.scene.resolution
        spp = term_passes(PRIMARY_TERM, settings, width * height)[0]
        if edges is None or not edges.meshes or len(views) * width * height * spp > AD_LANES:
            return False
        with dr.suspend_grad():
            P = dr.detach(edges.positions(mi.traverse(problem.scene.mi_scene)))
        return crossing_count(problem.scene.mi_scene, edges, P) == 0

    def primary(self, problem, views, iteration: int, settings, edges, delta: mi.Float) -> int:
        """The primary term's backward pass of Σ δ·I_primary over the batch ``views`` (into the
        scene's leaves), replayed; the curves are selected here (numpy, in each view's camera) and
        enter as padded arrays. Returns their number. :meth:`__call__` must have run for this scene."""
        if id(problem.scene.mi_scene) != self.scene_id:
            raise RuntimeError("FrozenBatch.primary: the batch's part must run first for this scene")
        width, height = problem.scene.resolution
        with dr.suspend_grad():
            P = dr.detach(edges.positions(mi.traverse(problem.scene.mi_scene)))
        parts = [camera_edge_ids(edges, P, self.origins[v], settings.max_depth >= 2,
                                 settings.estimator.primary_sampling) for v in views]
        total = sum(len(p["v0"]) for p in parts)
        if not total:
            return 0  # no curve in any view: the term adds nothing
        self.curve_slots = max(self.curve_slots, edge_slots(total))  # never fewer (see direct)
        packed, folds = packed_curves(parts, edge_shape_ids(problem.scene.mi_scene, edges), self.curve_slots)
        shape = PrimaryShape(id(problem.scene.mi_scene), width, height, len(views),
                             term_passes(PRIMARY_TERM, settings, width * height)[0], self.curve_slots,
                             tuple(edges.names), settings.max_depth, bool(problem.scene.config.hide_background),
                             folds)
        seed = views_seed(settings.seed, views, iteration, registry_term(PRIMARY_TERM).stream)
        self.primary_part(shape, problem.scene.mi_scene, self.table, mi.UInt32(views), opaque(seed), packed, delta)
        return total

    @property
    def n_recordings(self) -> int:
        """Recordings made so far (0 when not enabled)."""
        return self.interior.n_recordings + self.direct_part.n_recordings + self.primary_part.n_recordings


def interrupt_in(error: BaseException) -> KeyboardInterrupt | None:
    """The KeyboardInterrupt among ``error`` and the errors it was raised from (``__cause__``) or
    during (``__context__``, unless suppressed), at most five deep, or None."""
    for _ in range(5):
        if error is None or isinstance(error, KeyboardInterrupt):
            return error
        error = error.__cause__ if error.__cause__ is not None else (
            None if error.__suppress_context__ else error.__context__)
    return None


def opaque(value: int) -> mi.UInt32:
    """A number that changes from call to call as an evaluated array (a constant would be written
    into the kernels: compiled anew, or recorded again, for every value)."""
    return dr.opaque(mi.UInt32, value)


def _bind(body, shape):
    def bound(*args):
        return body(shape, *args)
    return bound
