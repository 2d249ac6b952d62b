#!/usr/bin/env python
"""What ``dr.freeze`` can and cannot do for an optimisation iteration (issue 38), measured on the
demo's experiment (``configs/reconstruct_bunny.yaml``, 64², initial shape, one Dr.Jit thread).

Three checks, each on one view's pass of the interior term followed by the L1 loss
ℓ = Σ|I − T| / (3WH) against that view's target T:

1. **Backward outside the frozen function.** ``f = dr.freeze(image)``, then ``dr.backward(ℓ(f()))``
   outside ``f``: the vertex gradient is compared with the traced one (Dr.Jit 1.5 does not carry
   the AD graph out of a frozen function; the gradient comes back as zeros, without an error).
2. **Backward inside the frozen function.** ``g = dr.freeze(λ: backward(ℓ(image)))``: the vertex
   gradient must equal the traced one bit for bit, for every view and seed.
3. **Time per view**, traced against frozen replay (after every view has been recorded once: a
   change of sensor re-records), side by side in one process, with the reference loop.

    .venv/bin/python benchmarks/freeze_probe.py [--json docs/benchmarks/freeze_probe.json]
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
from iteration_time import setup  # noqa: E402
from machine import reference_loop_seconds  # noqa: E402

from psdr_cli.estimators.camera import camera_rays  # noqa: E402
from psdr_cli.estimators.interior import radiance  # noqa: E402
from psdr_cli.support import backend  # noqa: E402


def interior_image(mi_scene, sensor, seed, spp: int = 1):
    """One pass of the interior term (as :func:`psdr_cli.estimators.interior.estimate`), seeded by
    an opaque UInt32 so that a frozen recording does not depend on the seed's value."""
    width, height = sensor.film().size()
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(seed, width * height * spp)
    ray, weight = camera_rays(sensor, sampler, width, height, spp)
    L = weight * radiance(mi_scene, sampler, ray, 2, ad=True)
    return dr.ravel(mi.Color3f([dr.block_sum(L[c], spp) / spp for c in range(3)]))


def l1(image, target):
    """ℓ = Σ|I − T| / N."""
    return dr.sum(dr.abs(image - target)) / dr.width(target)


def loss_and_backward(mi_scene, sensor, seed, target):
    """ℓ of one interior pass, its reverse-mode pass run here (into the scene's vertex leaf)."""
    loss = l1(interior_image(mi_scene, sensor, seed), target)
    dr.backward(loss)
    return dr.detach(loss)


class Probe:
    """The demo's scene with its vertex buffer as a fresh AD leaf per call."""

    def __init__(self, tmp: Path):
        _, _, self.problem, _, _, self.stage = setup(1, tmp)
        self.params = mi.traverse(self.problem.scene.mi_scene)
        self.V0 = dr.detach(mi.Float(self.params[self.problem.key]))

    def leaf(self):
        V = mi.Float(self.V0)
        dr.enable_grad(V)
        self.params[self.problem.key] = V
        self.params.update()
        return V

    def inputs(self, view: int, seed: int):
        return self.problem.scene.mi_scene, self.problem.scene.sensors[view], mi.UInt32(seed), self.stage.arrays[view]

    def gradient(self, fn, view: int, seed: int, backward_outside: bool = False):
        V = self.leaf()
        scene, sensor, s, target = self.inputs(view, seed)
        if backward_outside:
            loss = l1(fn(scene, sensor, s), target)
            dr.backward(loss)
        else:
            loss = fn(scene, sensor, s, target)
        g = dr.grad(V)
        dr.eval(g, loss)
        return float(loss[0]), np.asarray(g, np.float64)


def check_outside(probe: Probe) -> dict:
    frozen = dr.freeze(interior_image)
    traced = probe.gradient(interior_image, 0, 7, backward_outside=True)[1]
    out = probe.gradient(frozen, 0, 7, backward_outside=True)[1]
    return {"traced_abs_sum": float(np.abs(traced).sum()), "frozen_abs_sum": float(np.abs(out).sum())}


def check_inside(probe: Probe, frozen, views: int) -> dict:
    rows = []
    for seed in (11, 12):
        for v in range(views):
            la, ga = probe.gradient(loss_and_backward, v, seed)
            lb, gb = probe.gradient(frozen, v, seed)
            rows.append({"view": v, "seed": seed, "loss_equal": la == lb, "max_abs_diff": float(np.abs(ga - gb).max()),
                         "abs_sum": float(np.abs(ga).sum())})
    return {"rows": rows, "identical": all(r["loss_equal"] and r["max_abs_diff"] == 0.0 for r in rows)}


def time_per_view(probe: Probe, fn, views: int, rounds: int) -> float:
    dr.sync_thread()
    t0 = time.perf_counter()
    for i in range(rounds * views):
        probe.gradient(fn, i % views, 1000 + i)
    dr.sync_thread()
    return (time.perf_counter() - t0) / (rounds * views)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--rounds", type=int, default=6, help="timed passes over the views")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    result = {"drjit": dr.__version__, "mitsuba": mi.__version__, "reference_before": reference_loop_seconds()}
    with tempfile.TemporaryDirectory() as tmp, backend.optimization_threads():
        probe = Probe(Path(tmp))
        views = len(probe.stage.arrays)
        frozen = dr.freeze(loss_and_backward, warn_after=4 * views)
        result["backward_outside"] = check_outside(probe)
        for _ in range(2):  # record every (previous view, view) configuration; warm the kernel cache
            for v in range(views):
                probe.gradient(frozen, v, 1)
                probe.gradient(loss_and_backward, v, 1)
        result["recordings_after_warmup"] = frozen.n_recordings
        result["backward_inside"] = check_inside(probe, frozen, views)
        times = {"traced": [], "frozen": []}
        for _ in range(2):  # alternate, side by side
            times["traced"].append(time_per_view(probe, loss_and_backward, views, args.rounds))
            times["frozen"].append(time_per_view(probe, frozen, views, args.rounds))
        result["ms_per_view"] = {k: [t * 1e3 for t in v] for k, v in times.items()}
        result["recordings_after_timing"] = frozen.n_recordings
        probe.problem.release()
    result["reference_after"] = reference_loop_seconds()
    out = result["backward_outside"]
    print(f"backward outside the frozen function: |grad| traced {out['traced_abs_sum']:.6g}, "
          f"frozen {out['frozen_abs_sum']:.6g}")
    print(f"backward inside: bit-identical to traced over {len(result['backward_inside']['rows'])} (view, seed) "
          f"pairs: {result['backward_inside']['identical']}")
    print("ms per view (forward + backward), traced: " + ", ".join(f"{t:.1f}" for t in result["ms_per_view"]["traced"])
          + "; frozen: " + ", ".join(f"{t:.1f}" for t in result["ms_per_view"]["frozen"]))
    print(f"recordings: {result['recordings_after_warmup']} after warm-up, {result['recordings_after_timing']} after "
          f"timing; reference loop {result['reference_before']:.2f} s / {result['reference_after']:.2f} s")
    if args.json:
        args.json.write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
