#!/usr/bin/env python
"""Primal render time: one kernel per pass against one kernel per colour channel.

``estimators.interior.render_pass`` sums the samples of every pixel with ``dr.block_sum``, one
colour channel at a time. ``dr.block_sum`` evaluates its input, so unless the three channels of
the radiance L are evaluated together first, each sum traces the paths again (the renderer
before the fix). Both passes are timed here side by side on the same scene, view, samples and
seed, alternating, and their images compared (they must be equal: the same operations per
lane). Primal renders are what ``psdr render``, the finite differences of ``psdr grad --fd``,
the target images and the adjoint renders of ``psdr optimize`` spend their time in.

    .venv/bin/python benchmarks/render_passes.py configs/validation/*.yaml --spp 4096 --repeats 5
"""
from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from importlib import import_module
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from psdr_cli.estimators import interior  # noqa: E402
from psdr_cli.estimators.camera import camera_rays  # noqa: E402
from psdr_cli.estimators.passes import make_sampler  # noqa: E402
from psdr_cli.experiment.load import load_experiment  # noqa: E402
from psdr_cli.scene.build import build_scene  # noqa: E402
from psdr_cli.support import backend  # noqa: E402

rendering = import_module("psdr_cli.rendering.render")  # the module (the package's `render` is the API function)


def per_channel_pass(scene, sensor, width: int, height: int, spp: int, max_depth: int, seed: int) -> np.ndarray:
    """The pass before the fix: each channel's block sum evaluates (and traces) the paths itself."""
    sampler = make_sampler(seed, width * height * spp)
    ray, weight = camera_rays(sensor, sampler, width, height, spp)
    L = weight * interior.radiance(scene, sampler, ray, max_depth)
    sums = [dr.block_sum(L[c], spp) for c in range(3)]
    dr.eval(sums)
    return np.stack([np.asarray(s, np.float64) for s in sums], axis=-1).reshape(height, width, 3)


PASSES = {"one kernel per pass": interior.render_pass, "one kernel per channel": per_channel_pass}


def timed_render(scene, spp: int, seed: int, render_pass) -> tuple:
    """(seconds, image) of ``psdr_cli.rendering.render.render_view`` with ``render_pass`` as its pass."""
    rendering.render_pass = render_pass
    try:
        t0 = time.perf_counter()
        image = rendering.render_view(scene, 0, spp, seed=seed)
        return time.perf_counter() - t0, image
    finally:
        rendering.render_pass = interior.render_pass


def measure(config: Path, spp: int, repeats: int) -> dict:
    """Median seconds of each pass on view 0 of ``config`` and whether the images are equal."""
    exp = load_experiment(config)
    backend.activate(exp)
    scene = build_scene(exp)
    for fn in PASSES.values():  # compile both kernels before timing
        timed_render(scene, spp, exp.seed, fn)
    seconds = {name: [] for name in PASSES}
    equal = True
    for r in range(repeats):
        images = []
        for name, fn in PASSES.items():
            s, image = timed_render(scene, spp, exp.seed + r, fn)
            seconds[name].append(s)
            images.append(image)
        equal &= bool(np.array_equal(*images))
    median = {name: float(np.median(s)) for name, s in seconds.items()}
    return {"config": str(config), "film": list(scene.resolution), "max_depth": scene.config.max_depth, "spp": spp,
            "seconds": median, "speedup": median["one kernel per channel"] / median["one kernel per pass"],
            "equal_images": equal}


def write_report(rows: list, out: Path, spp: int, repeats: int):
    lines = ["# Primal render time: one kernel per pass against one per colour channel", "",
             f"`benchmarks/render_passes.py`, view 0 at {spp} spp, median of {repeats} renders each, alternating; "
             f"{mi.variant()}, {dr.thread_count()} Dr.Jit threads, {platform.processor() or platform.machine()}.", "",
             "| scene | film | max_depth | per pass (s) | per channel (s) | speedup | images equal |",
             "|---|---|---|---|---|---|---|"]
    for r in rows:
        s = r["seconds"]
        lines.append(f"| {Path(r['config']).stem} | {r['film'][0]}×{r['film'][1]} | {r['max_depth']} | "
                     f"{s['one kernel per pass']:.3f} | {s['one kernel per channel']:.3f} | {r['speedup']:.2f}× | "
                     f"{'yes' if r['equal_images'] else 'NO'} |")
    out.with_suffix(".md").write_text("\n".join(lines) + "\n")
    out.with_suffix(".json").write_text(json.dumps(rows, indent=1) + "\n")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("configs", nargs="+", type=Path)
    ap.add_argument("--spp", type=int, default=4096)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--out", type=Path, default=Path("docs/benchmarks/render_passes"))
    args = ap.parse_args()
    rows = []
    for config in args.configs:
        rows.append(measure(config, args.spp, args.repeats))
        r = rows[-1]
        print(f"{config}: {r['seconds']} speedup {r['speedup']:.2f}x equal {r['equal_images']}", flush=True)
    write_report(rows, args.out, args.spp, args.repeats)
    print(f"wrote {args.out.with_suffix('.md')}")


if __name__ == "__main__":
    main()
