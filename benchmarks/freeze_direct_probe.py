#!/usr/bin/env python
"""Can ``dr.freeze`` replay the direct boundary term's segments when the edge table changes?
(issue 38, stop 52: why psdr_cli/optimisation/frozen_batch.py serves only runs whose vertex buffer the
large-steps solve writes.)

The demo's scene (``configs/reconstruct_bunny.yaml``, 64², a noisy sphere), four views' lanes
(4·64² samples of the ``dir`` technique, no MIS), the cameras as data
(:class:`~psdr_cli.estimators.camera.CameraTable`). The frozen function takes the edge table as
arrays padded to a fixed length (``estimators.recorded_direct.padded_edges``) and the number of real edges as
an opaque array; it draws an edge ∝ length (``boundary_sampling.LengthDistribution``: no kernel
depends on the count), samples the wedge, and returns (lanes kept, Σ coef) of
:func:`~psdr_cli.estimators.direct.segment_weight` (``--level segment``) or only of the edge
draw, the wedge and the source ray (``--level ray``). Each trial drops 7 more edges from the end
of the table (same shape, same vertices) and compares the frozen call with the same function
traced.

    .venv/bin/python benchmarks/freeze_direct_probe.py [--level segment|ray] [--flag-off NAME]

Each call writes the scene's vertex buffer from a numpy array first (a fresh leaf, as a test
would). Measured (stop 52; Dr.Jit 1.5.0, Mitsuba 3.9.1, llvm_ad_rgb, 2 cores): ``--level ray``
replays right on every table; ``--level segment`` replays wrong (0 lanes kept where the traced
call keeps about 1000) on 3 of the 4 tables that differ from the one recorded; with
``--flag-off ValueNumbering`` right, with ``--flag-off ConstantPropagation`` still wrong. Other
levels (``motion``, ``backward``) replayed right or wrong from run to run. The interior term's
part replayed wrong in the same way once the vertex buffer was written from numpy (or a copy of
it) before each call, and right, bit for bit over 8 iterations of a moving shape, when the buffer
is written as the loop writes it, by the large-steps solve (tests/test_frozen_batch.py); so does
the direct term's part. The cause inside Dr.Jit was not found: psdr_cli/optimisation/frozen_batch.py serves
only runs whose unknown is the shape alone, written so.
"""
from __future__ import annotations

import argparse
from dataclasses import replace
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402
import numpy as np  # noqa: E402
from iteration_time import setup  # noqa: E402

from psdr_cli.support import backend  # noqa: E402
from psdr_cli.estimators.boundary_sampling import (BoundaryEdges, EdgeDraw, LengthDistribution, edge_list,  # noqa: E402
                                                   in_wedge, ray_origin, sample_edge_point, sample_wedge)
from psdr_cli.estimators.camera import CameraTable, LaneCameras  # noqa: E402
from psdr_cli.estimators.direct import direct_motion, segment_weight  # noqa: E402
from psdr_cli.estimators.passes import make_sampler  # noqa: E402
from psdr_cli.estimators.recording import padded_edges  # noqa: E402

SLOTS, SIZE, VIEWS = 512, 64, 4


def body(level, mi_scene, table, views, ids, flip, open_, count, seed):
    edges = BoundaryEdges(["bunny"], ids, open_, SLOTS, flip=flip)
    P = edges.positions(mi.traverse(mi_scene))
    with dr.suspend_grad():
        lengths = dr.norm(dr.gather(mi.Point3f, P, ids[1]) - dr.gather(mi.Point3f, P, ids[0]))
        sampler = make_sampler(seed, SIZE * SIZE * VIEWS)
        u1, u2 = sampler.next_1d(), sampler.next_2d()
        e = sample_edge_point(edges, P, LengthDistribution(lengths, count), u1)
        w, pdf = sample_wedge(e, u2)
        ok = in_wedge(e, w)
        if level == "ray":
            si = mi_scene.ray_intersect(mi.Ray3f(ray_origin(e), w), ok)
            return dr.sum(mi.Float(ok)), dr.sum(mi.Float(si.is_valid()))
        k = dr.arange(mi.UInt32, SIZE * SIZE * VIEWS) // dr.opaque(mi.UInt32, SIZE * SIZE)
        cams = LaneCameras.from_table(table, dr.gather(mi.UInt32, views, k))
        if level == "segment":
            coef, _, _, _, kept, _, _, _ = segment_weight(mi_scene, cams, e, w, (None, pdf), ray_origin(e), None, mis=False)
            return dr.sum(mi.Float(kept)), dr.sum(coef[0])
    draw = EdgeDraw(edges, P, LengthDistribution(lengths, count))
    v, pixel, kept, size = direct_motion(mi_scene, cams, draw, "dir", (u1, u2), 1.0, None, mis=False)
    if level == "motion":
        return dr.sum(mi.Float(kept)), dr.sum(dr.detach(v[0]))
    dr.backward(dr.sum(v[0] - dr.detach(v[0])))
    return dr.sum(mi.Float(kept)), dr.sum(dr.abs(dr.grad(P)))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--level", choices=("ray", "segment", "motion", "backward"), default="segment")
    ap.add_argument("--flag-off", default=None, help="a dr.JitFlag to switch off, e.g. ConstantPropagation")
    args = ap.parse_args(argv)
    if args.flag_off:
        dr.set_flag(getattr(dr.JitFlag, args.flag_off), False)
    with tempfile.TemporaryDirectory() as tmp, backend.optimization_threads():
        exp, _, problem, _, engine, _ = setup(1, Path(tmp))
        V = np.asarray(problem.vertices()) + np.random.default_rng(5).normal(0.0, 0.01, (len(problem.vertices()), 3))
        problem.scene.objects["bunny"].vertices = V
        edges = edge_list(problem.scene, engine.settings.estimator, False)
        table = CameraTable.of(problem.scene.sensors, SIZE, SIZE)

        def fn(*a):
            return body(args.level, *a)
        frozen = dr.freeze(fn)
        for trial in range(5):
            m = min(edges.count, SLOTS) - 7 * trial
            ids, flip, open_ = padded_edges(replace(edges, count=m), SLOTS)  # the first m edges
            out = []
            for f in (frozen, fn):
                leaf = mi.Float(np.ravel(V).astype(np.float32))
                dr.enable_grad(leaf)
                problem.params[problem.key] = leaf
                problem.params.update()
                a, b = f(problem.scene.mi_scene, table, mi.UInt32([0, 3, 5, 9]), ids, flip, open_,
                         dr.opaque(mi.UInt32, m), dr.opaque(mi.UInt32, 11))
                out.append((float(a[0]), float(b[0]), float(np.abs(np.asarray(dr.grad(leaf))).sum())))
            print(f"edges {m}: frozen (lanes, sum, leaf gradient) {out[0][0]:.0f}, {out[0][1]:.4f}, {out[0][2]:.4f}; "
                  f"traced {out[1][0]:.0f}, {out[1][1]:.4f}, {out[1][2]:.4f}; {'same' if out[0] == out[1] else 'DIFFERENT'}; "
                  f"recordings {frozen.n_recordings}")
        problem.release()


if __name__ == "__main__":
    main()
