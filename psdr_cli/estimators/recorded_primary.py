"""Owns the primary term's recorded part (:class:`PrimaryPart`, the interface of
:class:`.recording.RecordedPart`): its pass over a batch (the samples of its ``estimate_views``:
the draw, the side rays and radiances; the cameras from the run's table) and the backward pass of
Σ δ·I_primary into the scene's leaves, recorded per :class:`PrimaryShape` and replayed. Each
view's curves are selected on the host in numpy (:func:`.primary.primary_edge_ids`) and handed
over end to end as arrays padded to a power of two (:func:`packed_curves`); projected, weighed
and drawn on the device (:func:`.primary.draw_views`). An iteration with intersection curves
traces the term instead.
"""
from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from ..support.jitarray import jit_array
from .boundary_sampling import vertex_buffer
from .camera import CameraTable, LaneCameras
from .passes import AD_LANES, make_sampler
from .primary import (CurveCameras, CurveTable, SideReading, camera_edge_ids, crossing_count, curve_pass,
                      drawable, edge_shape_ids, view_starts)
from .recording import PaddedRecording, PassInputs, RecordedScene, adjoint_sum, opaque


@dataclass(frozen=True)
class PrimaryShape:
    """What a recording of the primary term's part is valid for: the scene object, the film, the
    batch size, the term's samples per pixel, the curve slots, the objects whose edges are curves,
    the path depth, whether camera rays that leave the scene see the background, and whether some
    curve folds back (:func:`.primary.fold_offsets` traced or not)."""
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
    :func:`.primary.camera_edge_ids`), end to end and padded to ``slots`` entries of
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


class PrimaryPart(PaddedRecording):
    """The primary term's recorded part (:class:`.recording.RecordedPart`); ``enabled`` false runs
    the same function traced every call."""

    def __init__(self, enabled: bool = True):
        super().__init__(primary_backward, enabled)

    def serves(self, scene, views, spp: int, edges) -> bool:
        """Whether the part can run on ``edges`` (the batch in one AD pass, edge objects with
        meshes, no intersection curve: those stay traced)."""
        width, height = scene.resolution
        if edges is None or not edges.meshes or len(views) * width * height * spp > AD_LANES:
            return False
        with dr.suspend_grad():
            P = dr.detach(edges.positions(mi.traverse(scene.mi_scene)))
        return crossing_count(scene.mi_scene, edges, P) == 0

    def run(self, recorded: RecordedScene, inputs: PassInputs, scene, *, edges, delta: mi.Float) -> int:
        """The backward pass of Σ δ·I_primary over the batch (into the scene's leaves), replayed;
        the curves are selected here (numpy, in each view's camera) and enter as padded arrays.
        Returns their number."""
        width, height = scene.resolution
        with dr.suspend_grad():
            P = dr.detach(edges.positions(mi.traverse(scene.mi_scene)))
        parts = [camera_edge_ids(edges, P, recorded.origins[v], inputs.max_depth >= 2,
                                 inputs.estimator.primary_sampling) for v in inputs.views]
        total = sum(len(p["v0"]) for p in parts)
        if not total:
            return 0  # no curve in any view: the term adds nothing
        slots = self.grown_slots(total)
        packed, folds = packed_curves(parts, edge_shape_ids(scene.mi_scene, edges), slots)
        shape = PrimaryShape(recorded.scene_id, width, height, len(inputs.views), inputs.spp, slots,
                             tuple(edges.names), inputs.max_depth, bool(scene.config.hide_background), folds)
        self.recording(shape, scene.mi_scene, recorded.table, mi.UInt32(inputs.views), opaque(inputs.seed), packed,
                       delta)
        return total


PART = PrimaryPart
