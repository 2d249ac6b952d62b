#!/usr/bin/env python
"""Can ``dr.freeze`` replay the direct boundary term's segments when the edge table changes?
(issue 38, stop 52: why the direct term stays traced in psdr_cli/frozen_batch.py.)

The demo's scene (``configs/reconstruct_bunny.yaml``, 64², a noisy sphere), four views' lanes
(4·64² samples of the ``dir`` technique, no MIS), the cameras as data
(:class:`~psdr_cli.estimators.camera.CameraTable`). The frozen function takes the edge table as
arrays padded to a fixed length (so that no input changes length) and the number of real edges
as an opaque array; it draws an edge ∝ length by inverse CDF with a fixed number of bisection
steps (no kernel depends on the count), samples the wedge, and returns (lanes kept, Σ coef) of
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
the direct term's part. The cause inside Dr.Jit was not found: psdr_cli/frozen_batch.py serves
only runs whose unknown is the shape alone, written so.
"""
from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402
import numpy as np  # noqa: E402
from iteration_time import setup  # noqa: E402

from psdr_cli import backend  # noqa: E402
from psdr_cli.estimators.boundary_sampling import (BoundaryEdges, edge_list, in_wedge, ray_origin,  # noqa: E402
                                                   sample_edge_point, sample_wedge)
from psdr_cli.estimators.camera import CameraTable, LaneCameras  # noqa: E402
from psdr_cli.estimators.direct import direct_motion, segment_weight  # noqa: E402
from psdr_cli.estimators.passes import make_sampler  # noqa: E402

SLOTS, STEPS, SIZE, VIEWS = 512, 24, 64, 4


class Lengths:
    """Edges drawn ∝ length, the count an array: first k with C_k > u·T, reused remainder."""

    def __init__(self, lengths, count):
        self.pmf, self.cdf = lengths, dr.cumsum(lengths)
        self.count, self.total = count, dr.gather(mi.Float, dr.cumsum(lengths), count - 1)

    def sum(self):
        return self.total

    def sample_reuse(self, u):
        x = u * self.total
        lo = dr.zeros(mi.UInt32, dr.width(u))
        size = dr.gather(mi.UInt32, self.count, lo)
        for _ in range(STEPS):
            half = size >> 1
            right = (size > 0) & (dr.gather(mi.Float, self.cdf, lo + half, size > 0) <= x)
            lo, size = dr.select(right, lo + half + 1, lo), dr.select(right, size - half - 1, half)
        pmf = dr.gather(mi.Float, self.pmf, lo)
        return lo, dr.clip((x - dr.gather(mi.Float, self.cdf, lo) + pmf) / dr.select(pmf > 0, pmf, 1.0), 0.0,
                           dr.one_minus_epsilon(mi.Float))


def body(level, mi_scene, table, views, ids, flip, open_, count, seed):
    edges = BoundaryEdges(["bunny"], ids, open_, SLOTS, flip=flip)
    P = edges.positions(mi.traverse(mi_scene))
    with dr.suspend_grad():
        lengths = dr.norm(dr.gather(mi.Point3f, P, ids[1]) - dr.gather(mi.Point3f, P, ids[0]))
        sampler = make_sampler(seed, SIZE * SIZE * VIEWS)
        u1, u2 = sampler.next_1d(), sampler.next_2d()
        e = sample_edge_point(edges, P, Lengths(lengths, count), u1)
        w, pdf = sample_wedge(e, u2)
        ok = in_wedge(e, w)
        if level == "ray":
            si = mi_scene.ray_intersect(mi.Ray3f(ray_origin(e), w), ok)
            return dr.sum(mi.Float(ok)), dr.sum(mi.Float(si.is_valid()))
        k = dr.arange(mi.UInt32, SIZE * SIZE * VIEWS) // dr.opaque(mi.UInt32, SIZE * SIZE)
        cams = LaneCameras.from_table(table, dr.gather(mi.UInt32, views, k))
        if level == "segment":
            coef, _, _, _, kept, _, _, _ = segment_weight(mi_scene, cams, e, w, None, pdf, False, ray_origin(e), None)
            return dr.sum(mi.Float(kept)), dr.sum(coef[0])
    v, pixel, kept, size = direct_motion(mi_scene, cams, edges, P, Lengths(lengths, count), "dir", False, u1, u2, 1.0,
                                         None)
    if level == "motion":
        return dr.sum(mi.Float(kept)), dr.sum(dr.detach(v[0]))
    dr.backward(dr.sum(v[0] - dr.detach(v[0])))
    return dr.sum(mi.Float(kept)), dr.sum(dr.abs(dr.grad(P)))


def padded(edges, m):
    """The first m edges, padded to SLOTS with edges of length 0 (device gathers)."""
    index = dr.arange(mi.UInt32, SLOTS)
    real = index < m
    at = dr.minimum(index, m - 1)
    ids = [dr.select(real, dr.gather(mi.UInt32, a, at), 0) for a in edges.ids]
    flip = real & dr.gather(mi.Bool, edges.flip, at)
    open_ = real & dr.gather(mi.Bool, edges.open, at)
    dr.eval(ids, flip, open_)
    return ids, flip, open_


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
            ids, flip, open_ = padded(edges, m)
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
