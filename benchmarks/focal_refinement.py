#!/usr/bin/env python
"""The focal length refined with the poses (``optimize.cameras.focal``): what it wins back when
every view's given focal length is 2 % too long, and what it costs per iteration.

1. **Dataset.** ``pose_refinement.py``'s (imported, not copied): Mitsuba's ``path`` integrator
   renders the textured glossy mesh under ``scenes/studio.exr``; the poses are exact.
2. **Wrong focal length.** A copy of its Blender folder whose ``camera_angle_x`` is that of a
   focal length f·(1 + ``--error``): 2 atan(tan(φ/2) / 1.02) (the images are the same files).
3. **Runs.** ``pose_refinement.py``'s experiment with ``optimize.cameras: {focal: true|false}``
   (the poses are refined in both), the same iterations.
4. **Scores.** Chamfer-L1 of the last mesh (as ``pose_refinement.py``), the recovered focal error
   s·(1 + error) − 1 (0: the true focal length; ``cameras.json``'s ``focal_scale``), the seconds
   per iteration, and the machine's 10⁷-step Python loop time.

    .venv/bin/python benchmarks/focal_refinement.py --meshes bunny --iterations 60 --size 64
"""
from __future__ import annotations

import argparse
import json
import math
import shutil
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import pose_refinement as pose  # noqa: E402
from machine import reference_loop_seconds  # noqa: E402


def wrong_focal_copy(dataset: Path, error: float) -> Path:
    """``<dataset>/focal_<error>/blender``: the Blender folder with camera_angle_x of f·(1 + error)."""
    out = dataset / f"focal_{error:+.3f}" / "blender"
    out.mkdir(parents=True, exist_ok=True)
    for item in (dataset / "blender").iterdir():
        target = out / item.name
        if item.suffix == ".json":
            doc = json.loads(item.read_text())
            doc["camera_angle_x"] = 2 * math.atan(math.tan(doc["camera_angle_x"] / 2) / (1 + error))
            target.write_text(json.dumps(doc, indent=1))
        elif not target.exists():
            target.symlink_to(item.resolve(), target_is_directory=item.is_dir())
    shutil.copy(dataset / "ground_truth.ply", out.parent / "ground_truth.ply")
    return out


def run(mesh: str, focal: bool, dataset: Path, args) -> dict:
    """One ``psdr optimize`` with ``optimize.cameras.focal: focal`` and its scores."""
    from photographs import shape_errors
    import yaml
    name = f"{mesh}_focal_{'on' if focal else 'off'}"
    cfg = pose.experiment(args.work / "configs" / f"{name}.yaml", name, dataset, args.work / "runs", "on",
                          args.iterations)
    data = yaml.safe_load(cfg.read_text())
    data["optimize"]["cameras"] = {"focal": focal, "focal_learning_rate": args.focal_learning_rate}
    cfg.write_text(yaml.safe_dump(data, sort_keys=False))
    log = args.work / "logs" / f"{name}.log"
    log.parent.mkdir(parents=True, exist_ok=True)
    log.write_text("")
    rc, seconds = pose.psdr("optimize", cfg, "--iterations", args.iterations, log=log)
    run_dir = args.work / "runs" / name
    out = {"mesh": mesh, "focal": focal, "returncode": rc, "seconds": seconds}
    if rc != 0 or not pose.finished(run_dir, args.iterations):
        out["error"] = pose.tail(log)
        return out
    out.update(pose.iteration_seconds(run_dir))
    out["chamfer_l1"] = float(shape_errors(run_dir, dataset.parent / "ground_truth.ply")[-1][1])
    views = json.loads((run_dir / "cameras.json").read_text())["views"]
    scale = views[0]["correction"].get("focal_scale", 1.0)
    out["focal_error"] = scale * (1 + args.error) - 1
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, default=pose.ROOT / "docs" / "benchmarks")
    ap.add_argument("--work", type=Path, default=pose.ROOT / "runs" / "bench_focal_refinement")
    ap.add_argument("--meshes", nargs="+", default=["bunny"], choices=pose.MESHES)
    ap.add_argument("--error", type=float, default=0.02, help="the given focal length's relative error")
    ap.add_argument("--iterations", type=int, default=150)
    ap.add_argument("--focal-learning-rate", type=float, default=2e-3)
    ap.add_argument("--views", type=int, default=24)
    ap.add_argument("--holdout", type=int, default=8)
    ap.add_argument("--size", type=int, default=96)
    ap.add_argument("--spp", type=int, default=256)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    reference_s = reference_loop_seconds()
    rows = []
    for mesh in args.meshes:
        folder = args.work / "datasets" / mesh
        pose.make_dataset(folder, mesh, args)
        dataset = wrong_focal_copy(folder, args.error)
        for focal in (False, True):
            rows.append(run(mesh, focal, dataset, args))
            print(json.dumps(rows[-1]), flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "focal_refinement.json").write_text(json.dumps(
        {"reference_loop_seconds": reference_s, "args": {k: str(v) for k, v in vars(args).items()}, "runs": rows},
        indent=1))
    print(f"reference loop (10^7 steps): {reference_s:.2f} s")


if __name__ == "__main__":
    main()
