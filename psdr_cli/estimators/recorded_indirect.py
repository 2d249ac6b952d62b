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

from .camera import CameraTable
from .indirect import MIN_DEPTH, indirect_samples
from .recording import EdgePart, PassInputs, RecordedScene, adjoint_sum, edge_batch


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
    """The indirect term's pass over the batch (the samples of its ``estimate_views``, each
    detector walk connected to its view's row of ``table``: :func:`.recording.edge_batch`) and the
    backward pass of Σ δ·I_indirect into the scene's leaves."""
    b = edge_batch(shape, mi_scene, table, views, seed, padded)
    samples = indirect_samples(mi_scene, b.lanes, b.edges, b.P, b.n, b.sampler, shape.max_depth, distr=b.distr)
    dr.backward(adjoint_sum(delta, samples))
    return padded[3]  # (a frozen function returns something)


class IndirectPart(EdgePart):
    """The indirect term's recorded part (:class:`.recording.RecordedPart`); ``enabled`` false runs
    the same function traced every call."""

    def __init__(self, enabled: bool = True):
        super().__init__(indirect_backward, enabled)

    def run(self, recorded: RecordedScene, inputs: PassInputs, scene, *, edges, delta: mi.Float) -> int:
        """The backward pass of Σ δ·I_indirect over the batch (into the scene's leaves), replayed;
        returns the number of edges (0, and nothing run, below depth :data:`.indirect.MIN_DEPTH`: the term is
        0 there)."""
        if inputs.max_depth < MIN_DEPTH:
            return 0
        width, height = scene.resolution
        shape = IndirectShape(recorded.scene_id, width, height, len(inputs.views), inputs.spp, inputs.max_depth,
                              tuple(edges.names), self.grown_slots(edges.count))
        return self.replay(shape, recorded, inputs, scene, edges, delta)


PART = IndirectPart
