#!/usr/bin/env python
"""Reconstruction from photographs psdr did not render, against psdr's own route on the same
mesh, cameras and lighting, at equal iterations.

1. ``benchmarks/photo_dataset.py`` renders the Stanford bunny with Mitsuba's own ``path``
   integrator (max_depth 4) under ``scenes/studio.exr`` from ``--views`` cameras, and writes the
   views as a Blender / NeRF-synthetic dataset (RGBA PNGs) and as a COLMAP text model (JPEGs over
   a backdrop plus mask PNGs); every ``--holdout``-th view is held out.
2. Runs of ``psdr optimize``, all with the experiment ``configs/photos/bunny_blender.yaml``'s
   estimator, schedule and learning rates, and the same seed:

   - **own**: psdr's own route: targets rendered by psdr from the ground-truth mesh with the
     dataset's training cameras (in the same normalised frame, background hidden, same film),
     the initial shape a sphere of radius ½ (no masks, so no hull and no silhouette loss);
   - **blender** / **colmap**: the dataset routes (photographs decoded, masks, silhouette loss,
     the visual hull as the initial shape);
   - **blender-sphere**: the Blender route from the same sphere as ``own`` (no hull).
3. Each run's meshes: Chamfer-L1 and Hausdorff against the ground truth (in the dataset's
   coordinates, normalised by the ground truth's bounding box) and held-out PSNR / SSIM / mask
   IoU (``psdr evaluate`` on the dataset experiment).

Outputs: ``<out>/photographs.md``, ``photographs.json``, and a picture of held-out strips.

    .venv/bin/python benchmarks/photographs.py --out docs/benchmarks --iterations 200
"""
from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from machine import reference_loop_seconds  # noqa: E402
import yaml

ROOT = Path(__file__).resolve().parents[1]


def dataset_config(dataset: Path, out: Path, iterations: int, name: str, downsample: int, **dataset_keys) -> Path:
    """The example experiment on ``dataset`` (absolute paths), written to ``out``."""
    data = yaml.safe_load((ROOT / "configs" / "photos" / "bunny_blender.yaml").read_text())
    data["name"] = name
    data["output"] = str(out / "runs")
    data["scene"]["emitters"][0]["file"] = str(ROOT / "scenes" / "studio.exr")
    data["optimize"]["target"]["dataset"] = {"path": str(dataset), "downsample": downsample, **dataset_keys}
    data["optimize"]["iterations"] = iterations
    data["optimize"]["checkpoint_every"] = max(iterations // 4, 1)
    path = out / f"{name}.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def own_route(exp, ground_truth: Path, folder: Path):
    """The dataset experiment with psdr's own targets: rendered from the ground truth (mapped into
    the normalised frame) with the same cameras, film and hidden background; a sphere to start."""
    from psdr_cli.config.objects import MeshSpec, TransformConfig
    from psdr_cli.experiment.dataset_frame import to_normalised
    from psdr_cli.scene.meshes import read_mesh_file, write_ply
    V, F = read_mesh_file(ground_truth)
    path = folder / "ground_truth_normalised.ply"
    write_ply(path, to_normalised(V, exp.optimize.target_dataset.frame), F)
    opt = replace(exp.optimize, target_dataset=None, target_mesh=MeshSpec(key="optimize.target.mesh", file=path),
                  target_spp=256, init=MeshSpec(key="optimize.init.mesh", shape="sphere",
                                                params={"radius": 0.5, "subdivisions": 3}),
                  init_transform=TransformConfig())
    true_bsdf = replace(exp.scene.objects[0].bsdf, params={"reflectance": (0.7, 0.6, 0.5)})  # photo_dataset's
    objects = [replace(o, bsdf=true_bsdf) if o.name == opt.object else o for o in exp.scene.objects]
    return replace(exp, name=exp.name.replace("blender", "own"), optimize=opt, scene=replace(exp.scene, objects=objects))


def sphere_start(exp):
    """The dataset experiment from the sphere ``own_route`` starts from (no visual hull)."""
    from psdr_cli.config.objects import MeshSpec, TransformConfig
    opt = replace(exp.optimize, init=MeshSpec(key="optimize.init.mesh", shape="sphere",
                                              params={"radius": 0.5, "subdivisions": 3}),
                  init_transform=TransformConfig())
    return replace(exp, name=exp.name + "_sphere", optimize=opt)


def shape_errors(run_dir: Path, ground_truth: Path, frame=None) -> list:
    """[(iteration, Chamfer-L1, Hausdorff)] of a run's checkpoints against the ground truth; the
    own route's meshes are in the normalised frame and are mapped back with ``frame``."""
    from psdr_cli.commands import evaluate as ev
    from psdr_cli.experiment.dataset_frame import to_dataset
    from psdr_cli.run_folder.checkpoints import run_checkpoints
    reference = ev.load(ground_truth)
    rows = []
    for iteration, path in run_checkpoints(run_dir):
        V, F = ev.load(path)
        d = ev.distance((to_dataset(V, frame), F), reference, 50_000)
        rows.append((iteration, d.chamfer_l1, d.hausdorff))
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "benchmarks")
    ap.add_argument("--work", type=Path, default=ROOT / "runs" / "bench_photographs")
    ap.add_argument("--views", type=int, default=40)
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--downsample", type=int, default=2)
    ap.add_argument("--holdout", type=int, default=8)
    ap.add_argument("--iterations", type=int, default=200)
    ap.add_argument("--routes", nargs="+", default=["own", "blender", "colmap", "blender-sphere"])
    args = ap.parse_args(argv)
    args.work, args.out = args.work.resolve(), args.out.resolve()
    import photo_dataset
    from psdr_cli import api
    from psdr_cli.commands.evaluate import evaluate_held_out
    from psdr_cli.experiment.load import load_experiment
    args.work.mkdir(parents=True, exist_ok=True)
    data = args.work / "dataset"
    if not (data / "dataset.json").exists():
        photo_dataset.main(["--out", str(data), "--views", str(args.views), "--size", str(args.size),
                            "--holdout", str(args.holdout)])
    gt = data / "ground_truth.ply"
    blender = load_experiment(dataset_config(data / "blender", args.work, args.iterations, "photos_blender",
                                             args.downsample))
    colmap = load_experiment(dataset_config(data / "colmap", args.work, args.iterations, "photos_colmap",
                                            args.downsample, holdout_every=args.holdout))
    experiments = {"own": own_route(blender, gt, args.work), "blender": blender, "colmap": colmap,
                   "blender-sphere": sphere_start(blender)}
    reference_s = reference_loop_seconds()
    results = {}
    for route in args.routes:
        exp = experiments[route]
        t = time.perf_counter()
        run = api.optimize(exp)
        seconds = time.perf_counter() - t
        frame = blender.optimize.target_dataset.frame if route == "own" else None
        errors = shape_errors(exp.run_dir, gt, frame)
        held = None
        if route != "own":
            held = evaluate_held_out(exp).rows
        results[route] = {"seconds": seconds, "optimisation_seconds": run.seconds, "chamfer": errors,
                          "held_out": held, "run": str(exp.run_dir)}
        print(f"{route}: {seconds:.0f} s, Chamfer-L1 {errors[0][1]:.5f} -> {errors[-1][1]:.5f}", flush=True)
    write_report(args, results, reference_s)


def write_report(args, results: dict, reference_s: float):
    """photographs.md and photographs.json in ``args.out``."""
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "photographs.json").write_text(json.dumps({"args": {k: str(v) for k, v in vars(args).items()},
                                                           "reference_loop_s": reference_s,
                                                           "results": results}, indent=1))
    own = results.get("own", {}).get("chamfer", [[0, None, None]])[-1][1]
    blender = results.get("blender", {}).get("chamfer", [[0, None, None]])[-1][1]
    lines = ["# Reconstruction from photographs (benchmarks/photographs.py)", "",
             f"{args.views} views of {args.size}² rendered by Mitsuba's `path` integrator (max_depth 4), "
             f"downsampled {args.downsample}×, every {args.holdout}th view held out; {args.iterations} iterations "
             f"per route; reference 10⁷-step Python loop: {reference_s:.2f} s.", "",
             "| route | seconds | Chamfer-L1 first | Chamfer-L1 last | ratio to own | Hausdorff last | "
             "held-out PSNR first → last | PSNR in mask | SSIM | mask IoU |",
             "|---|---:|---:|---:|---:|---:|---|---|---|---|"]
    for route, r in results.items():
        first, last = r["chamfer"][0], r["chamfer"][-1]
        ratio = f"{last[1] / own:.2f}" if own else "—"
        held = r["held_out"]
        cells = ["—"] * 4
        if held:
            f2 = lambda k: f"{held[0][k]:.2f} → {held[-1][k]:.2f}"  # noqa: E731
            f4 = lambda k: f"{held[0][k]:.4f} → {held[-1][k]:.4f}"  # noqa: E731
            cells = [f2("psnr"), f2("psnr_mask"), f4("ssim"), f4("iou")]
        lines.append(f"| {route} | {r['seconds']:.0f} | {first[1]:.5f} | {last[1]:.5f} | {ratio} | {last[2]:.4f} | "
                     + " | ".join(cells) + " |")
    if own and blender:
        lines += ["", f"Blender route / own route: {blender / own:.2f} (target ≤ 1.25); "
                      f"COLMAP / Blender: {results['colmap']['chamfer'][-1][1] / blender:.2f} (target ≤ 1.1)"
                  if "colmap" in results else ""]
    picture = held_out_picture(results, args.out / "photographs_heldout.png")
    if picture:
        lines += ["", f"![held-out views]({picture.name})", "",
                  "Held-out views of the Blender route: for the initial mesh (the visual hull, top rows) and the "
                  "last mesh (bottom rows), target | render | |error|."]
    (args.out / "photographs.md").write_text("\n".join(lines) + "\n")
    print((args.out / "photographs.md").read_text())


def held_out_picture(results: dict, path: Path):
    """The Blender route's held-out strips (initial and last mesh) stacked into one PNG."""
    import cv2
    run = results.get("blender", {}).get("run")
    if not run:
        return None
    strips = sorted((Path(run) / "held_out").glob("*_view_*.png"))
    if not strips:
        return None
    rows = [cv2.imread(str(p), cv2.IMREAD_COLOR) for p in strips]
    image = np.repeat(np.repeat(np.concatenate(rows, 0), 2, 0), 2, 1)
    cv2.imwrite(str(path), image)
    return path


if __name__ == "__main__":
    import sys
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    main()
