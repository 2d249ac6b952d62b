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

5. **Ambiguity** (``--ambiguity``, no optimisation): how much of a focal scale's effect on the
   masks the object scaled by the same factor about the cameras' look-at point reproduces, with
   the cameras fixed: the pixels where the mask of focal s and the true mask differ, against
   those where the masks of focal s and of the scaled object differ (Mitsuba's ``aov``
   shape index, 64 spp, box filter; the first ``--ambiguity-views`` training views).

    .venv/bin/python benchmarks/focal_refinement.py --meshes bunny --iterations 60 --size 64
    .venv/bin/python benchmarks/focal_refinement.py --meshes bunny cow --ambiguity
"""
from __future__ import annotations

import argparse
import json
import math
import shutil
import sys
from pathlib import Path

import numpy as np

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


def coverage(V, F, fov_deg: float, cam_to_world, size: int) -> np.ndarray:
    """(size, size) coverage of the mesh (V, F) through a Blender camera (OpenGL axes,
    horizontal field of view ``fov_deg``): Mitsuba's ``aov`` shape index is 0 on the mesh."""
    import mitsuba as mi
    mesh = mi.Mesh("object", len(V), len(F))
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(np.ascontiguousarray(V, np.float32).ravel())
    params["faces"] = mi.UInt32(np.ascontiguousarray(F, np.uint32).ravel())
    params.update()
    opengl_to_mitsuba = np.diag([-1.0, 1.0, -1.0, 1.0])
    scene = mi.load_dict({"type": "scene", "object": mesh, "integrator": {"type": "aov", "aovs": "s:shape_index"},
                          "camera": {"type": "perspective", "fov": fov_deg, "fov_axis": "x",
                                     "to_world": mi.ScalarTransform4f(np.asarray(cam_to_world) @ opengl_to_mitsuba),
                                     "film": {"type": "hdrfilm", "width": size, "height": size,
                                              "rfilter": {"type": "box"}}}})
    return np.asarray(mi.render(scene, spp=64))[..., 0]


def ambiguity(folder: Path, scale: float, views: int) -> dict:
    """{"focal_px", "residual_px", "share"}: mask pixels changed by a focal scale ``scale``, and
    those where it differs from the object scaled by ``scale`` about the look-at point."""
    import mitsuba as mi
    import trimesh
    mi.set_variant("llvm_ad_rgb")
    doc = json.loads((folder / "blender" / "transforms_train.json").read_text())
    mesh = trimesh.load(folder / "ground_truth.ply", process=False)
    V, F = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    poses = [np.asarray(f["transform_matrix"], np.float64) for f in doc["frames"]][:views]
    made = json.loads((folder / "dataset.json").read_text())
    centre, size = np.asarray(made["look_at"], np.float64), int(made["settings"]["size"])
    fov = math.degrees(doc["camera_angle_x"])
    zoomed = math.degrees(2 * math.atan(math.tan(math.radians(fov) / 2) / scale))
    focal_px = residual_px = 0.0
    for M in poses:
        truth, zoom = coverage(V, F, fov, M, size), coverage(V, F, zoomed, M, size)
        grown = coverage(centre + scale * (V - centre), F, fov, M, size)
        focal_px += float(np.abs(zoom - truth).sum())
        residual_px += float(np.abs(zoom - grown).sum())
    return {"focal_px": focal_px, "residual_px": residual_px, "share": residual_px / max(focal_px, 1e-30)}


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
    ap.add_argument("--ambiguity", action="store_true", help="only the focal / object-size ambiguity of the masks")
    ap.add_argument("--ambiguity-views", type=int, default=12)
    args = ap.parse_args(argv)
    if args.ambiguity:
        for mesh in args.meshes:
            folder = args.work / "datasets" / mesh
            pose.make_dataset(folder, mesh, args)
            print(mesh, json.dumps(ambiguity(folder, 1 + args.error, args.ambiguity_views)), flush=True)
        return
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
