#!/usr/bin/env python
"""The heavy tail of the interior term at depth ≥ 3 on a concave object, over seeds.

From the first surface-to-surface segment on, the material-form interior term carries
d log|n_y·ω| at the vertex y a bounce reaches; BSDF sampling draws grazing hits in proportion to
|n_y·ω|, so the estimate is unbiased but its variance diverges (logarithmically): rare samples
dwarf the rest (docs/optimize.md, "Outlier clipping at depth ≥ 3"). This benchmark measures that
tail where the loop meets it, so that an estimator meant to remove it can be judged:

- **Scene.** The thick cup of ``unknown_light.py`` (its profile revolved, 64 sections; diffuse,
  reflectance (0.8, 0.7, 0.6)) under ``scenes/studio.exr`` at 0.8, seen from above at 40° field of
  view, ``--size``² pixels, ``scene.max_depth`` ``--depth``; θ stretches the cup along z
  (``parameter: {kind: scale, axis: [0, 0, 1]}``).
- **Estimate.** ``psdr grad``'s forward-mode gradient image of the interior term alone
  (``api.gradient_images``) at ``--spp`` samples per pixel, for ``--seeds`` seeds.
- **Scores.** Per seed the 99.9th percentile and the largest |pixel| of the gradient image, and the
  image's sum; over the seeds their medians, how many seeds have a pixel above 20 and above 100,
  the largest pixels, and the sum's mean, standard error and median (the mean's error is what a
  heavy tail inflates).

Outputs ``<out>/interior_tail.json`` and ``.md`` (with the machine's 10⁷-step loop time).

    .venv/bin/python benchmarks/interior_tail.py --seeds 40
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent))
import unknown_light  # noqa: E402
from machine import reference_loop_seconds  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def experiment(cup: Path, args, seed: int) -> dict:
    """The experiment dictionary of the measurement (module docstring)."""
    return {"name": "cup_tail", "output": str(args.work / "runs"), "seed": seed,
            "scene": {"film": {"width": args.size, "height": args.size}, "max_depth": args.depth,
                      "cameras": [{"origin": [0, -3.2, 3.0], "target": [0, 0, 0.5], "fov": 40}],
                      "emitters": [{"type": "envmap", "file": str(ROOT / "scenes" / "studio.exr"), "scale": 0.8}],
                      "objects": [{"name": "cup", "mesh": {"file": str(cup)},
                                   "bsdf": {"type": "diffuse", "reflectance": [0.8, 0.7, 0.6]}}]},
            "parameter": {"object": "cup", "kind": "scale", "axis": [0, 0, 1]},
            "estimator": {"spp": args.spp, "terms": ["interior"]}}


def gradient_image(cup: Path, args, seed: int) -> tuple:
    """(the interior term's gradient image, seconds) of one seed."""
    from psdr_cli import api
    from psdr_cli.experiment.load import load_experiment
    path = args.work / "configs" / f"cup_tail_{seed}.yaml"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(yaml.safe_dump(experiment(cup, args, seed), sort_keys=False))
    t = time.perf_counter()
    estimate = api.gradient_images(load_experiment(path), terms=["interior"])["interior"]
    return np.asarray(estimate.gradient, np.float64), time.perf_counter() - t


def summary(images: list, seconds: list) -> dict:
    """The scores over seeds (module docstring)."""
    a = [np.abs(g) for g in images]
    p999 = np.array([np.percentile(x, 99.9) for x in a])
    top = np.array([x.max() for x in a])
    sums = np.array([g.sum() for g in images])
    return {"seeds": len(images), "seconds_per_seed": float(np.mean(seconds)),
            "p999": p999.tolist(), "max": top.tolist(), "sum": sums.tolist(),
            "p999_median": float(np.median(p999)), "max_median": float(np.median(top)),
            "seeds_above_20": int((top > 20).sum()), "seeds_above_100": int((top > 100).sum()),
            "largest": np.sort(top)[-4:][::-1].tolist(), "sum_mean": float(sums.mean()),
            "sum_error": float(sums.std(ddof=1) / np.sqrt(len(sums))) if len(sums) > 1 else float("nan"), "sum_median": float(np.median(sums))}


def write_report(args, result: dict, reference_s: float):
    (args.out / "interior_tail.json").write_text(json.dumps(
        {"args": {k: str(v) for k, v in vars(args).items()}, "reference_loop_seconds": reference_s, **result}, indent=1))
    r = result
    lines = ["# The interior term's tail at depth ≥ 3 (benchmarks/interior_tail.py)", "",
             f"The thick cup (diffuse, `scenes/studio.exr` at 0.8), {args.size}² pixels, max_depth {args.depth}, "
             f"θ a vertical stretch; the interior term's forward gradient image at {args.spp} spp, {r['seeds']} seeds "
             f"({r['seconds_per_seed']:.1f} s each; reference 10⁷-step Python loop: {reference_s:.2f} s).", "",
             "| 99.9th percentile of a pixel's size (median over seeds) | largest pixel's size (median) "
             "| seeds with a pixel > 20 | > 100 | the four largest | image sum: mean ± error (median) |",
             "|---:|---:|---:|---:|---|---|",
             f"| {r['p999_median']:.2f} | {r['max_median']:.1f} | {r['seeds_above_20']} / {r['seeds']} | "
             f"{r['seeds_above_100']} / {r['seeds']} | {', '.join(f'{x:.0f}' for x in r['largest'])} | "
             f"{r['sum_mean']:.1f} ± {r['sum_error']:.1f} ({r['sum_median']:.1f}) |"]
    (args.out / "interior_tail.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "benchmarks")
    ap.add_argument("--work", type=Path, default=ROOT / "runs" / "bench_interior_tail")
    ap.add_argument("--seeds", type=int, default=40)
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--size", type=int, default=48)
    ap.add_argument("--depth", type=int, default=4)
    args = ap.parse_args(argv)
    args.out, args.work = args.out.resolve(), args.work.resolve()
    args.out.mkdir(parents=True, exist_ok=True)
    import mitsuba as mi
    mi.set_variant("llvm_ad_rgb")
    reference_s = reference_loop_seconds()
    cup = args.work / "cup.ply"
    if not cup.exists():
        cup.parent.mkdir(parents=True, exist_ok=True)
        unknown_light.cup_mesh(cup)
    images, seconds = [], []
    for seed in range(args.seeds):
        image, s = gradient_image(cup, args, seed)
        images.append(image)
        seconds.append(s)
        print(f"seed {seed}: largest |pixel| {np.abs(image).max():.1f}", flush=True)
    write_report(args, summary(images, seconds), reference_s)


if __name__ == "__main__":
    main()
