"""An iteration's edge table and intersection search, computed on a worker thread while the
iteration's first kernels run. Reads the meshes' buffers and the cameras on the main thread; the
worker touches only numpy copies of them.

Both are numpy work on the current vertices (:func:`psdr_cli.estimators.boundary_sampling.edge_rows`,
:func:`psdr_cli.geometry.intersections.intersection_segments`), rebuilt every iteration; the optimisation
loop runs Dr.Jit on one thread (for bit-reproducible runs), and Dr.Jit releases Python's GIL while
a kernel runs, so the worker's numpy and the adjoint render's kernels share the two halves of the
time they took one after the other. The worker's own code calls no Dr.Jit or Mitsuba function
(Dr.Jit holds its own lock while a kernel runs, so a second thread calling it would only wait;
Python's garbage collector may still free a Dr.Jit object there, which Dr.Jit's locked reference
counts allow): the main thread reads the meshes' buffers and the cameras before, and uploads the
table after (:meth:`GeometryAhead.edges`). The results are those of
:func:`~.estimators.boundary_sampling.edge_list` and of the primary term's own search
(:func:`~.estimators.primary.scene_segments` finds the search under its digest and does not run
it again).
"""
from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import drjit as dr

from ..estimators.boundary_sampling import BoundaryEdges, camera_origins, edge_rows
from ..estimators.primary import mesh_arrays, mesh_shapes, segments_key
from ..geometry.intersections import intersection_segments


class GeometryAhead:
    """The edge table (``estimator.edge_sort``, ``estimator.chains``) of ``scene`` and, when
    ``segments`` (the primary term runs) and some object has edges, the intersection search among
    its meshes (the primary term searches only then), started on the worker thread."""

    def __init__(self, scene, estimator, sort: bool, segments: bool):
        cameras = camera_origins(scene.mi_scene)
        self.buffers, arrays = [], None
        names = [n for n, om in scene.objects.items() if om.edges]
        if segments and names:
            shapes = mesh_shapes(scene.mi_scene, names)
            positions = [dr.detach(s.vertex_positions_buffer()) for s in shapes]
            faces = [s.faces_buffer() for s in shapes]
            self.buffers, arrays = positions + faces, mesh_arrays(positions, faces)
        self.arrays = arrays
        # a thread of its own per iteration (~0.1 ms to start): nothing outlives the iteration, and a
        # process forked meanwhile inherits no pool whose thread it lacks
        pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="psdr-geometry")
        self.future = pool.submit(geometry, dict(scene.objects), cameras, sort, estimator.chains.max_turn,
                                  estimator.chains.max_length, arrays)
        pool.shutdown(wait=False)  # the thread ends with its one job

    def edges(self) -> BoundaryEdges:
        """The edge table as Dr.Jit arrays, its intersection search kept for the primary term
        (waits for the worker; its exceptions are raised here)."""
        rows, key, segments = self.future.result()
        edges = BoundaryEdges.from_rows(rows)
        if key is not None:
            edges.segments[key] = segments
            # the buffers read here, kept as primary.scene_meshes would read them again
            edges.remembered("meshes", self.buffers, lambda: self.arrays)
        return edges


def geometry(objects: dict, cameras, sort: bool, max_turn: float, max_length: int, arrays):
    """(edge rows, digest of ``arrays``, their intersection segments): numpy only (the worker's)."""
    rows = edge_rows(objects, cameras, sort, max_turn, max_length)
    if arrays is None:
        return rows, None, None
    return rows, segments_key(arrays), intersection_segments([V for V, _ in arrays], [F for _, F in arrays])
