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

from .camera import CameraTable
from .direct import direct_samples
from .recording import EdgePart, PassInputs, RecordedScene, adjoint_sum, edge_batch

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
    from ``table``: :func:`.recording.edge_batch`) and the backward pass of Σ δ·I_direct into the
    scene's leaves."""
    b = edge_batch(shape, mi_scene, table, views, seed, padded)
    samples = direct_samples(mi_scene, b.lanes, b.edges, b.P, b.n, b.sampler, shape.sampling, distr=b.distr)
    dr.backward(adjoint_sum(delta, samples))
    return padded[3]  # (a frozen function returns something)


class DirectPart(EdgePart):
    """The direct term's recorded part (:class:`.recording.RecordedPart`); ``enabled`` false runs
    the same function traced every call."""

    def __init__(self, enabled: bool = True):
        super().__init__(direct_backward, enabled)

    def run(self, recorded: RecordedScene, inputs: PassInputs, scene, *, edges, delta: mi.Float) -> int:
        """The backward pass of Σ δ·I_direct over the batch (into the scene's leaves), replayed;
        returns the number of edges."""
        width, height = scene.resolution
        shape = DirectShape(recorded.scene_id, width, height, len(inputs.views), inputs.spp,
                            inputs.estimator.sampling, tuple(edges.names), self.grown_slots(edges.count))
        return self.replay(shape, recorded, inputs, scene, edges, delta)


PART = DirectPart
