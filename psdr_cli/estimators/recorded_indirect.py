"""Owns the indirect term's recorded part (:class:`IndirectPart`, the interface of
:class:`.recording.RecordedPart`): its pass over a batch (the samples of its ``estimate_views``:
the edge draw, the source subpath and the detector's walk; the cameras from the run's table) and
the backward pass of Σ δ·I_indirect into the scene's leaves, recorded per :class:`IndirectShape`
and replayed. The edges enter as arrays padded to a power of two
(:func:`.recording.padded_edges`) and are drawn ∝ length by
:class:`.boundary_sampling.LengthDistribution`, whose kernels do not depend on their number. The
subpaths are unrolled in Python over the path depth (max_depth − 1 source segments, max_depth − 2
detector lengths), so the depth is part of the structure.
"""
from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from .boundary_sampling import BoundaryEdges, length_distribution
from .camera import CameraTable, LaneCameras, ViewLanes
from .indirect import MIN_DEPTH, indirect_samples
from .passes import AD_LANES, make_sampler
from .recording import MAX_EDGES, PaddedRecording, PassInputs, RecordedScene, adjoint_sum, opaque, padded_edges


@dataclass(frozen=True)
class IndirectShape:
    """What a recording of the indirect term's part is valid for: the scene object (its emitters,
    BSDFs and shapes), the film, the batch size, the term's samples per pixel, the path depth (the
    unrolled subpaths), the objects whose edges are drawn (their vertex buffers, in order) and the
    slots of the padded edge arrays."""
    scene_id: int
    width: int
    height: int
    views: int
    spp: int
    max_depth: int
    names: tuple
    slots: int


def indirect_backward(shape: IndirectShape, mi_scene, table: CameraTable, views: mi.UInt32, seed: mi.UInt32,
                      padded: tuple, delta: mi.Float):
    """The indirect term's pass over the batch (the samples of its ``estimate_views``, lane i of
    view ``views[i // N]``, N = spp·W·H, its detector walk connected to that view's row of
    ``table``) and the backward pass of Σ δ·I_indirect into the scene's leaves. The edges
    ``padded`` = (ids: their six vertex-id columns, flip, open, count; ``shape.slots`` entries, of
    which ``count`` real ones, at least one, and the rest of length 0:
    :func:`.recording.padded_edges`) index the concatenated vertex buffers of ``shape.names``."""
    ids, flip, open_, count = padded
    edges = BoundaryEdges(list(shape.names), ids, open_, shape.slots, flip=flip)  # (the real count: ``count``)
    P = edges.positions(mi.traverse(mi_scene))
    n = shape.spp * shape.width * shape.height
    sampler = make_sampler(seed, n * shape.views)
    k = dr.arange(mi.UInt32, n * shape.views) // n
    lanes = ViewLanes(LaneCameras.from_table(table, dr.gather(mi.UInt32, views, k)), k, shape.views)
    samples = indirect_samples(mi_scene, lanes, edges, P, n, sampler, shape.max_depth,
                               distr=length_distribution(edges, P, count))
    dr.backward(adjoint_sum(delta, samples))
    return count  # (a frozen function returns something)


class IndirectPart(PaddedRecording):
    """The indirect term's recorded part (:class:`.recording.RecordedPart`); ``enabled`` false runs
    the same function traced every call."""

    def __init__(self, enabled: bool = True):
        super().__init__(indirect_backward, enabled)

    def serves(self, scene, views, spp: int, edges) -> bool:
        """Whether the part can run on ``edges`` (the batch in one AD pass, 1 to
        :data:`.recording.MAX_EDGES` edges)."""
        width, height = scene.resolution
        return edges is not None and 0 < edges.count < MAX_EDGES and len(views) * width * height * spp <= AD_LANES

    def run(self, recorded: RecordedScene, inputs: PassInputs, scene, *, edges, delta: mi.Float) -> int:
        """The backward pass of Σ δ·I_indirect over the batch (into the scene's leaves), replayed;
        returns the number of edges (0, and nothing run, below depth :data:`.indirect.MIN_DEPTH`: the term is
        0 there)."""
        if inputs.max_depth < MIN_DEPTH:
            return 0
        width, height = scene.resolution
        shape = IndirectShape(recorded.scene_id, width, height, len(inputs.views), inputs.spp, inputs.max_depth,
                              tuple(edges.names), self.grown_slots(edges.count))
        ids, flip, open_ = padded_edges(edges, shape.slots)
        self.recording(shape, scene.mi_scene, recorded.table, mi.UInt32(inputs.views), opaque(inputs.seed),
                       (ids, flip, open_, opaque(edges.count)), delta)
        return edges.count


PART = IndirectPart
