"""Owns the direct term's recorded part (:class:`DirectPart`, the interface of
:class:`.recording.RecordedPart`): its pass over a batch (the samples of its ``estimate_views``,
the cameras from the run's table) and the backward pass of Σ δ·I_direct into the scene's leaves,
recorded per :class:`DirectShape` and replayed. The edges enter as arrays padded to a power of
two (:func:`.recording.padded_edges`) and are drawn ∝ length by
:class:`.boundary_sampling.LengthDistribution`, whose kernels do not depend on their number.
"""
from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from .boundary_sampling import BoundaryEdges, length_distribution
from .camera import CameraTable, LaneCameras, ViewLanes
from .direct import direct_samples
from .passes import AD_LANES, make_sampler
from .recording import MAX_EDGES, PaddedRecording, PassInputs, RecordedScene, adjoint_sum, opaque, padded_edges

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


def direct_backward(shape: DirectShape, mi_scene, table: CameraTable, views: mi.UInt32, seed: mi.UInt32,
                    padded: tuple, delta: mi.Float):
    """The direct term's pass over the batch (the samples of its ``estimate_views``, the cameras
    from ``table``) and the backward pass of Σ δ·I_direct into the scene's leaves. The edges
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
    samples = direct_samples(mi_scene, lanes, edges, P, n, sampler, shape.sampling,
                             distr=length_distribution(edges, P, count))
    dr.backward(adjoint_sum(delta, samples))
    return count  # (a frozen function returns something)


class DirectPart(PaddedRecording):
    """The direct term's recorded part (:class:`.recording.RecordedPart`); ``enabled`` false runs
    the same function traced every call."""

    def __init__(self, enabled: bool = True):
        super().__init__(direct_backward, enabled)

    def serves(self, scene, views, spp: int, edges) -> bool:
        """Whether the part can run on ``edges`` (the batch in one AD pass, 1 to
        :data:`.recording.MAX_EDGES` edges)."""
        width, height = scene.resolution
        return edges is not None and 0 < edges.count < MAX_EDGES and len(views) * width * height * spp <= AD_LANES

    def run(self, recorded: RecordedScene, inputs: PassInputs, scene, *, edges, delta: mi.Float) -> int:
        """The backward pass of Σ δ·I_direct over the batch (into the scene's leaves), replayed;
        returns the number of edges."""
        width, height = scene.resolution
        shape = DirectShape(recorded.scene_id, width, height, len(inputs.views), inputs.spp,
                            inputs.estimator.sampling, tuple(edges.names), self.grown_slots(edges.count))
        ids, flip, open_ = padded_edges(edges, shape.slots)
        self.recording(shape, scene.mi_scene, recorded.table, mi.UInt32(inputs.views), opaque(inputs.seed),
                       (ids, flip, open_, opaque(edges.count)), delta)
        return edges.count


PART = DirectPart
