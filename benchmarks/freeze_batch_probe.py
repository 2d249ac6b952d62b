#!/usr/bin/env python
"""Can ``dr.freeze`` record a whole mini-batch of the loop, and how often does it record again?
(issue 38; the one-view probe is ``freeze_probe.py``.)

The demo's experiment (``configs/reconstruct_bunny.yaml``, 64², initial shape, one Dr.Jit
thread): a batch of 4 of its 12 views traced as one wavefront (the interior term's
:func:`~psdr_cli.estimators.camera.views_camera_rays` and
:func:`~psdr_cli.estimators.interior.radiance`, 1 spp), the L1 loss
ℓ = Σ|I − T| / N against the batch's targets and ``dr.backward(ℓ)`` inside the frozen function,
into the scene's vertex buffer as the AD leaf. The sensors of the batch are passed as Mitsuba
objects, as the terms take them today. Three checks:

1. **Same gradient**: every 8th batch, the frozen call's loss and vertex gradient against the
   traced function's (bit for bit).
2. **Recordings**: ``n_recordings`` after each of the loop's batches (``iteration.batch_views``,
   seed 0), first from a cold start and then after a warm-up that passed every sensor twice.
3. **Time per batch**, traced against frozen, alternated, in one process.

And the same function with **the cameras as data** (``batch_loss_tables``): every view's frame
and intrinsics in arrays (:class:`~psdr_cli.estimators.camera.LaneCameras` of all views, built
once), the batch as an array of view indices, each lane's ray from its view's row of the tables:
its recordings over the same batches, its gradient against its own traced version, its time.

    .venv/bin/python benchmarks/freeze_batch_probe.py [--json docs/benchmarks/freeze_batch_probe.json]
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402
import numpy as np  # noqa: E402
from freeze_probe import Probe  # noqa: E402
from machine import reference_loop_seconds  # noqa: E402

from psdr_cli.estimators.camera import LaneCameras, views_camera_rays  # noqa: E402
from psdr_cli.estimators.interior import radiance  # noqa: E402
from psdr_cli.optimisation.iteration import batch_views  # noqa: E402
from psdr_cli.support import backend  # noqa: E402

VIEWS, BATCH, SIZE = 12, 4, 64


def batch_loss(mi_scene, sensors, seed, targets):
    """ℓ of one 1-spp interior pass of ``sensors`` in one wavefront, its backward pass run here."""
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(seed, SIZE * SIZE * len(sensors))
    ray, weight = views_camera_rays(sensors, sampler, SIZE, SIZE, 1)
    L = weight * radiance(mi_scene, sampler, ray, 2, ad=True)
    image = dr.ravel(mi.Color3f(L[0], L[1], L[2]))
    loss = dr.sum(dr.abs(image - targets)) / dr.width(targets)
    dr.backward(loss)
    return dr.detach(loss)


def camera_tables(sensors) -> dict:
    """Every view's frame (4 columns) and intrinsics (tan(fov/2), principal point, clip distances),
    one row per view, as :class:`LaneCameras` gathers them."""
    cams = LaneCameras(sensors, dr.arange(mi.UInt32, len(sensors)), SIZE, SIZE)
    tables = {f"axis{j}": cams.axes[j] for j in range(4)}
    tables.update(tan_half=cams.tan_half, cx=cams.cx, cy=cams.cy, near=cams.near, far=cams.far)
    dr.eval(tables)
    return tables


def table_rays(tables: dict, views: mi.UInt32, sampler, spp: int):
    """The lanes of ``views`` (view-major, W·H·spp each) and their camera rays through their pixels,
    their cameras gathered from ``tables`` (weight 1: Mitsuba's perspective camera)."""
    per_view = SIZE * SIZE * spp
    idx = dr.arange(mi.UInt32, per_view * dr.width(views))
    k = idx // dr.opaque(mi.UInt32, per_view)
    pixel = (idx - k * dr.opaque(mi.UInt32, per_view)) // dr.opaque(mi.UInt32, spp)
    pos = mi.Point2f(mi.Float(pixel % SIZE), mi.Float(pixel // SIZE)) + sampler.next_2d()
    sampler.next_1d()  # the wavelength sample views_camera_rays draws
    view = dr.gather(mi.UInt32, views, k)
    cams = LaneCameras.__new__(LaneCameras)
    cams.width = cams.height = SIZE
    cams.axes = [dr.gather(mi.Vector3f, tables[f"axis{j}"], view) for j in range(4)]
    cams.tan_half, cams.cx, cams.cy, cams.near, cams.far = (
        dr.gather(mi.Float, tables[key], view) for key in ("tan_half", "cx", "cy", "near", "far"))
    return cams(pos)


def batch_loss_tables(mi_scene, tables, views, seed, targets):
    """:func:`batch_loss` with the batch's cameras gathered from ``tables`` by view index."""
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(seed, SIZE * SIZE * dr.width(views))
    ray = table_rays(tables, views, sampler, 1)
    L = radiance(mi_scene, sampler, ray, 2, ad=True)
    image = dr.ravel(mi.Color3f(L[0], L[1], L[2]))
    loss = dr.sum(dr.abs(image - targets)) / dr.width(targets)
    dr.backward(loss)
    return dr.detach(loss)


class Batches:
    """The probe's scene and targets; ``gradient`` runs a batch through ``fn`` on a fresh leaf."""

    def __init__(self, probe: Probe):
        self.probe = probe
        self.targets = [np.asarray(t, np.float32) for t in probe.stage.arrays]
        self.tables = camera_tables(probe.problem.scene.sensors)

    def gradient(self, fn, views, seed: int):
        V = self.probe.leaf()
        targets = mi.Float(np.concatenate([self.targets[v] for v in views]))
        sensors = [self.probe.problem.scene.sensors[v] for v in views]
        loss = fn(self.probe.problem.scene.mi_scene, sensors, mi.UInt32(seed), targets)
        g = dr.grad(V)
        dr.eval(g, loss)
        return float(loss[0]), np.asarray(g, np.float64)

    def gradient_tables(self, fn, views, seed: int):
        V = self.probe.leaf()
        targets = mi.Float(np.concatenate([self.targets[v] for v in views]))
        loss = fn(self.probe.problem.scene.mi_scene, self.tables, mi.UInt32(views), mi.UInt32(seed), targets)
        g = dr.grad(V)
        dr.eval(g, loss)
        return float(loss[0]), np.asarray(g, np.float64)


def recordings(batches: Batches, frozen, first: int, count: int, tables: bool = False) -> list:
    out = []
    run = batches.gradient_tables if tables else batches.gradient
    for it in range(first, first + count):
        run(frozen, batch_views(0, it, VIEWS, BATCH), 100 + it)
        out.append(frozen.n_recordings)
    return out


def cameras_as_data(batches: Batches, count: int) -> dict:
    """Recordings, gradient and time of :func:`batch_loss_tables`, frozen against traced."""
    frozen = dr.freeze(batch_loss_tables, warn_after=10 * count)
    out = {"recordings": recordings(batches, frozen, 0, count, tables=True)}
    rows = []
    for it in range(7, count, 8):
        views = batch_views(0, it, VIEWS, BATCH)
        la, ga = batches.gradient_tables(batch_loss_tables, views, 100 + it)
        lb, gb = batches.gradient_tables(frozen, views, 100 + it)
        lc, gc = batches.gradient(batch_loss, views, 100 + it)
        rows.append({"views": views, "loss_equal": la == lb, "max_abs_diff": float(np.abs(ga - gb).max()),
                     "abs_sum": float(np.abs(ga).sum()), "against_sensor_objects_max_abs_diff":
                     float(np.abs(ga - gc).max()), "against_sensor_objects_loss": [la, lc]})
    out["same_gradient"] = {"rows": rows, "identical": all(r["loss_equal"] and r["max_abs_diff"] == 0.0
                                                           for r in rows)}
    times = {"traced": [], "frozen": []}
    for _ in range(2):
        for name, fn in (("traced", batch_loss_tables), ("frozen", frozen)):
            dr.sync_thread()
            t0 = time.perf_counter()
            for it in range(count, 2 * count):  # batches not seen before
                batches.gradient_tables(fn, batch_views(0, it, VIEWS, BATCH), 900 + it)
            dr.sync_thread()
            times[name].append((time.perf_counter() - t0) / count * 1e3)
    out["ms_per_batch_new_batches"] = times
    out["recordings_at_end"] = frozen.n_recordings
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--batches", type=int, default=40)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    result = {"drjit": dr.__version__, "mitsuba": mi.__version__, "reference_before": reference_loop_seconds()}
    with tempfile.TemporaryDirectory() as tmp, backend.optimization_threads():
        batches = Batches(Probe(Path(tmp)))
        cold = dr.freeze(batch_loss, warn_after=10 * args.batches)
        result["recordings_cold"] = recordings(batches, cold, 0, args.batches)
        rows = []
        for it in range(7, args.batches, 8):
            views = batch_views(0, it, VIEWS, BATCH)
            la, ga = batches.gradient(batch_loss, views, 100 + it)
            lb, gb = batches.gradient(cold, views, 100 + it)
            rows.append({"views": views, "loss_equal": la == lb, "max_abs_diff": float(np.abs(ga - gb).max()),
                         "abs_sum": float(np.abs(ga).sum())})
        result["same_gradient"] = {"rows": rows, "identical": all(r["loss_equal"] and r["max_abs_diff"] == 0.0
                                                                   for r in rows)}
        warm = dr.freeze(batch_loss, warn_after=10 * args.batches)
        for _ in range(2):
            for first in range(0, VIEWS, BATCH):
                batches.gradient(warm, list(range(first, first + BATCH)), 7)
        result["recordings_after_warmup"] = warm.n_recordings
        result["recordings_warm"] = recordings(batches, warm, 0, args.batches)
        times = {"traced": [], "frozen": []}
        for _ in range(2):
            for name, fn in (("traced", batch_loss), ("frozen", warm)):
                dr.sync_thread()
                t0 = time.perf_counter()
                for it in range(args.batches):  # batches the warm function has recorded
                    batches.gradient(fn, batch_views(0, it, VIEWS, BATCH), 500 + it)
                dr.sync_thread()
                times[name].append((time.perf_counter() - t0) / args.batches * 1e3)
        result["ms_per_batch_recorded"] = times
        result["cameras_as_data"] = cameras_as_data(batches, args.batches)
        batches.probe.problem.release()
    result["reference_after"] = reference_loop_seconds()
    print("recordings, cold start:", result["recordings_cold"])
    print(f"recordings after a warm-up over every sensor ({result['recordings_after_warmup']}):",
          result["recordings_warm"])
    print("frozen gradient bit-identical to the traced one:", result["same_gradient"]["identical"],
          f"({len(rows)} batches)")
    print("ms per batch on recorded batches, traced:", ", ".join(f"{t:.1f}" for t in times["traced"]),
          "; frozen:", ", ".join(f"{t:.1f}" for t in times["frozen"]))
    data = result["cameras_as_data"]
    print("cameras as data: recordings", data["recordings"], "then", data["recordings_at_end"],
          "after the timed new batches; bit-identical to its traced version:", data["same_gradient"]["identical"])
    print("cameras as data, ms per batch on new batches, traced:",
          ", ".join(f"{t:.1f}" for t in data["ms_per_batch_new_batches"]["traced"]), "; frozen:",
          ", ".join(f"{t:.1f}" for t in data["ms_per_batch_new_batches"]["frozen"]))
    print("against the sensor objects' rays: max |dg|",
          max(r["against_sensor_objects_max_abs_diff"] for r in data["same_gradient"]["rows"]))
    print(f"reference loop {result['reference_before']:.2f} s / {result['reference_after']:.2f} s")
    if args.json:
        args.json.write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
