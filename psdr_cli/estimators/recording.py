"""Owns the machinery of the recorded (``dr.freeze``) passes of an iteration: a frozen function per
structure (:class:`Recording`), the inputs they share (:class:`RecordedScene`, :class:`PassInputs`),
and the interface of a term's recorded part (:class:`RecordedPart`). Reads nothing of the run;
the parts write the gradients of the scene's leaf buffers.

A term whose pass over a batch can be recorded has a module ``recorded_<term>.py`` declaring
``PART``, a class with the methods of :class:`RecordedPart`; :data:`.registry.RECORDED` lists
them in the order their backward passes run.
"""
from __future__ import annotations

import gc
from dataclasses import dataclass
from typing import Protocol

import drjit as dr
import mitsuba as mi

from .boundary_sampling import SEARCH_STEPS, BoundaryEdges, length_distribution
from .camera import CameraTable, LaneCameras, ViewLanes
from .passes import AD_LANES, make_sampler

#: Fewest slots of a recorded part's padded arrays (:func:`edge_slots`).
MIN_EDGE_SLOTS = 256
#: Most edges a part's draw serves (boundary_sampling.SEARCH_STEPS bisection steps).
MAX_EDGES = 1 << SEARCH_STEPS


@dataclass
class RecordedScene:
    """What the recorded parts of one scene and stage share: the scene object's id (a remesh
    builds a new scene), the run's cameras as a table (:class:`.camera.CameraTable`) and each
    camera's origin."""
    scene_id: int
    table: CameraTable
    origins: list


@dataclass
class PassInputs:
    """One iteration's inputs to a recorded part: the batch's ``views``, the pass's ``seed`` and
    samples per pixel ``spp``, the experiment's ``estimator`` settings and the path depth."""
    views: list
    seed: int
    spp: int
    estimator: object
    max_depth: int


class RecordedPart(Protocol):
    """A term's pass over a batch, recorded per structure and replayed:

        serves(scene, views, spp, edges) -> bool
            whether the part can run on this iteration's ``edges`` (unguided passes only: the
            caller asks that first)
        run(recorded: RecordedScene, inputs: PassInputs, scene, *, edges, delta) -> int
            the backward pass of Σ δ·I_term over the batch into the scene's leaves; returns the
            number of samples' sources it drew from (edges or curves)
        reset()                      drop the recordings (a new scene or stage)
        n_recordings -> int          recordings made so far
    """

    def serves(self, scene, views, spp: int, edges) -> bool: ...

    def run(self, recorded: RecordedScene, inputs: PassInputs, scene, *, edges, delta) -> int: ...

    def reset(self): ...

    @property
    def n_recordings(self) -> int: ...


def edge_slots(count: int) -> int:
    """The length of a recorded part's padded arrays of ``count`` entries (edges, curves):
    ``count`` rounded up to a power of two (at least :data:`MIN_EDGE_SLOTS`), so that one
    recording serves every count up to it with inputs of one length (a part keeps the largest a
    scene needed)."""
    return max(MIN_EDGE_SLOTS, 1 << (count - 1).bit_length())


def padded_edges(edges: BoundaryEdges, slots: int) -> tuple:
    """(ids, flip, open) of ``edges`` padded to ``slots`` entries with edges of length 0 (both
    ends vertex 0: never drawn, :class:`.boundary_sampling.LengthDistribution`)."""
    index = dr.arange(mi.UInt32, slots)
    count = opaque(edges.count)  # (a constant would compile this kernel anew for every count)
    real = index < count
    at = dr.minimum(index, count - 1)
    ids = [dr.select(real, dr.gather(mi.UInt32, a, at), 0) for a in edges.ids]
    flip = real & dr.gather(mi.Bool, edges.flip, at)
    open_ = real & dr.gather(mi.Bool, edges.open, at)
    dr.eval(ids, flip, open_)
    return ids, flip, open_


class PaddedRecording:
    """What a recorded part keeps between iterations: its frozen function (:class:`Recording` of
    ``body``; ``enabled`` false: traced every call) and the slots of its padded arrays, the most
    this scene has needed (never fewer: a count going back and forth across a power of two would
    record again each time)."""

    def __init__(self, body, enabled: bool = True):
        self.recording = Recording(body, enabled)
        self.slots = 0

    def reset(self):
        """Drop the recordings and the slots (a new scene or stage)."""
        self.recording.reset()
        self.slots = 0

    @property
    def n_recordings(self) -> int:
        return self.recording.n_recordings

    def grown_slots(self, count: int) -> int:
        """The slots for ``count`` entries (:func:`edge_slots`), kept if more than before."""
        self.slots = max(self.slots, edge_slots(count))
        return self.slots


class EdgePart(PaddedRecording):
    """A boundary term's recorded part over padded edge arrays (the direct and indirect terms'):
    it serves a batch in one AD pass with 1 to :data:`MAX_EDGES` edges, and replays its body on a
    record of what the recording is valid for (with ``names`` and ``slots`` among its fields)."""

    def serves(self, scene, views, spp: int, edges) -> bool:
        """Whether the part can run on ``edges`` (the batch in one AD pass, 1 to
        :data:`MAX_EDGES` edges)."""
        width, height = scene.resolution
        return edges is not None and 0 < edges.count < MAX_EDGES and len(views) * width * height * spp <= AD_LANES

    def replay(self, shape, recorded: RecordedScene, inputs: PassInputs, scene, edges, delta: mi.Float) -> int:
        """Run the body, recorded for ``shape``, on the batch's views and seed and ``edges`` padded
        to ``shape.slots``; returns the number of edges."""
        ids, flip, open_ = padded_edges(edges, shape.slots)
        self.recording(shape, scene.mi_scene, recorded.table, mi.UInt32(inputs.views), opaque(inputs.seed),
                       (ids, flip, open_, opaque(edges.count)), delta)
        return edges.count


@dataclass
class EdgeBatch:
    """What a recorded boundary pass draws from: the padded ``edges`` and their AD vertex
    positions ``P``, the ``n`` = spp·W·H lanes per view, the ``sampler``, the ``lanes``' cameras
    (lane i of view ``views[i // n]``, from the run's table) and the edges' length distribution
    ``distr`` over the real ``count`` of them."""
    edges: BoundaryEdges
    P: object
    n: int
    sampler: mi.Sampler
    lanes: ViewLanes
    distr: object


def edge_batch(shape, mi_scene, table: CameraTable, views: mi.UInt32, seed: mi.UInt32, padded: tuple) -> EdgeBatch:
    """The :class:`EdgeBatch` of a recorded boundary pass. ``padded`` = (ids: the edges' six
    vertex-id columns, flip, open, count; ``shape.slots`` entries, of which ``count`` real ones,
    at least one, and the rest of length 0: :func:`padded_edges`) index the concatenated vertex
    buffers of ``shape.names``; ``shape`` also gives the film, the batch size and the samples."""
    ids, flip, open_, count = padded
    edges = BoundaryEdges(list(shape.names), ids, open_, shape.slots, flip=flip)  # (the real count: ``count``)
    P = edges.positions(mi.traverse(mi_scene))
    n = shape.spp * shape.width * shape.height
    k = dr.arange(mi.UInt32, n * shape.views) // n
    lanes = ViewLanes(LaneCameras.from_table(table, dr.gather(mi.UInt32, views, k)), k, shape.views)
    return EdgeBatch(edges, P, n, make_sampler(seed, n * shape.views), lanes, length_distribution(edges, P, count))


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
