#!/usr/bin/env python
"""Captures scored as the field scores them (Stanford-ORB's three parts) for psdr's photograph
route: a constant albedo against a recovered texture, known light against an unknown environment
(started from the true map's mean, or from the photographs alone, with no light given).

1. **Datasets.** The textured, glossy objects of ``pose_refinement.py`` (the bunny and the cow from
   the pymeshlab wheel, per-vertex colour patches as a principled ``base_color``, roughness 0.35,
   Mitsuba's ``path`` integrator under ``scenes/studio.exr`` × 0.8, 24 training and 4 held-out
   views, 96², exact poses), and for each a **relighting split**: the same object rendered by the
   same integrator under a sun-and-sky map of our own (``sun.exr``, written here) from 12 other
   cameras.
2. **Runs** (``psdr optimize``, 150 iterations, the example's schedule, ``cameras: off``): albedo
   ``constant`` (one RGB value) or ``texture`` (64²), roughness unknown, and the light
   ``known`` (the studio map), ``unknown`` (``optimize.envmap`` started from the studio map's
   mean) or ``no probe`` (no emitter given: the map starts from the photographs,
   ``psdr_cli/optimisation/photo_light.py``).
3. **Scores.** Geometry: Chamfer-L1 (normalised by the ground truth's bounding box), and from the
   held-out cameras the scale-invariant depth error and the normal angle (``psdr evaluate
   --reference``). Novel views: PSNR and SSIM inside the held-out masks. Relighting: PSNR-H,
   PSNR-L and SSIM of the relit object against the relighting split after the per-channel scale
   (``psdr evaluate --relight``). LPIPS is not measured (its network weights cannot be fetched).

    .venv/bin/python benchmarks/capture_scores.py                   # writes docs/benchmarks/capture_scores.*
    .venv/bin/python benchmarks/capture_scores.py --meshes bunny --iterations 20 --out /tmp/cs
"""
from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import numpy as np
import yaml

import photo_dataset
import pose_refinement as pr
from machine import reference_loop_seconds

ROOT = Path(__file__).resolve().parents[1]
ALBEDOS = ("constant", "texture")
LIGHTS = ("known", "unknown", "no probe")
RELIGHT_VIEWS = 12


def sun_map(path: Path) -> Path:
    """A 128 × 64 lat-long EXR: a dim sky and a warm sun 40° above the horizon."""
    from psdr_cli.support import fileio
    H, W = 64, 128
    theta = (np.arange(H) + 0.5) / H * np.pi
    phi = (np.arange(W) + 0.5) / W * 2 * np.pi
    sky = (0.05 + 0.15 * np.cos(theta / 2) ** 2)[:, None, None] * np.array([0.5, 0.7, 1.0])
    texels = np.broadcast_to(sky, (H, W, 3)).copy()
    sun = np.exp(-(((theta[:, None] - np.radians(50)) / 0.1) ** 2 + ((phi[None, :] - 2.0) / 0.1) ** 2))
    texels += 60.0 * sun[..., None] * np.array([1.0, 0.85, 0.6])
    fileio.write_rgb_exr(path, texels)
    return path


def relight_split(folder: Path, mesh: str, info: dict, sun: Path, args) -> Path:
    """The object under ``sun`` from RELIGHT_VIEWS other cameras, as a Blender dataset."""
    import mitsuba as mi
    out = folder / "relight"
    if (out / "transforms_train.json").exists():
        return out
    mi.set_variant("llvm_ad_rgb")
    V, F = pr.load_mesh(mesh)
    poses = photo_dataset.camera_poses(RELIGHT_VIEWS, info["look_at"], info["radius"], args.seed + 101)
    bsdf = {"type": "principled", "base_color": {"type": "mesh_attribute", "name": "vertex_color"},
            "roughness": pr.ROUGHNESS}
    images = photo_dataset.render_views(V, F, poses, pr.FOV, args.size, args.spp, sun, None, max_depth=3,
                                        bsdf=bsdf, vertex_colors=pr.patch_colours(V, args.seed + 17))
    photo_dataset.write_blender(out, images, poses, pr.FOV, 10 ** 6)
    return out


def experiment(path: Path, name: str, dataset: Path, output: Path, albedo: str, light: str, iterations: int) -> Path:
    """The run of one (albedo, light) pair (module docstring, step 2)."""
    pr.experiment(path, name, dataset, output, "off", iterations)
    data = yaml.safe_load(path.read_text())
    opt = data["optimize"]
    opt["albedo"] = {"texture": [64, 64]} if albedo == "texture" else {"init": [0.5, 0.5, 0.5]}
    if light == "known":
        opt.pop("envmap")
    elif light == "no probe":
        data["scene"].pop("emitters")
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def run(mesh: str, albedo: str, light: str, dataset: Path, relight: Path, sun: Path, args) -> dict:
    """One run and its three kinds of scores."""
    from photographs import shape_errors
    name = f"{mesh}_{albedo}_{light.replace(' ', '_')}"
    cfg = experiment(args.work / "configs" / f"{name}.yaml", name, dataset / "blender", args.work / "runs",
                     albedo, light, args.iterations)
    log = args.work / "logs" / f"{name}.log"
    log.parent.mkdir(parents=True, exist_ok=True)
    log.write_text("")
    rc, seconds = pr.psdr("optimize", cfg, "--iterations", args.iterations, log=log)
    result = {"mesh": mesh, "albedo": albedo, "light": light, "seconds": seconds, "returncode": rc}
    run_dir = args.work / "runs" / name
    if rc != 0:
        result["error"] = pr.tail(log)
        print(f"{name}: FAILED ({result['error']})", flush=True)
        return result
    result.update(pr.iteration_seconds(run_dir))
    result["chamfer_l1"] = float(shape_errors(run_dir, dataset / "ground_truth.ply")[-1][1])
    held = args.work / "evaluate" / f"{name}.json"
    held.parent.mkdir(parents=True, exist_ok=True)
    pr.psdr("evaluate", cfg, "--reference", dataset / "ground_truth.ply", "--json", held, log=log)
    last = json.loads(held.read_text())["meshes"][-1]
    result["novel"] = {k: last.get(k) for k in ("psnr_mask", "ssim_mask", "iou", "depth_error", "normal_deg")}
    relit = args.work / "evaluate" / f"{name}_relit.json"
    pr.psdr("evaluate", cfg, "--relight", relight, "--envmap", sun, "--envmap-scale", 0.8, "--json", relit, log=log)
    row = json.loads(relit.read_text())["relight"][-1]
    result["relit"] = {k: row[k] for k in ("psnr_h", "psnr_l", "ssim", "iou")}
    print(f"{name}: Chamfer-L1 {result['chamfer_l1']:.5f}, novel PSNR {result['novel']['psnr_mask']:.2f}, "
          f"relit PSNR-H {result['relit']['psnr_h']:.2f} / PSNR-L {result['relit']['psnr_l']:.2f}", flush=True)
    return result


def table(results: list) -> list:
    """Stanford-ORB's form: geometry, novel views, relighting; one row per run."""
    fmt = lambda v, f: "—" if v is None else format(v, f)  # noqa: E731
    lines = ["| mesh | albedo | light | Chamfer-L1 | depth error | normal ° | novel PSNR | novel SSIM | PSNR-H | "
             "PSNR-L | relit SSIM | s/iteration |", "|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in results:
        if "error" in r:
            lines.append(f"| {r['mesh']} | {r['albedo']} | {r['light']} | failed: {r['error']} |")
            continue
        n, rl = r["novel"], r["relit"]
        lines.append(f"| {r['mesh']} | {r['albedo']} | {r['light']} | {r['chamfer_l1']:.5f} | "
                     f"{fmt(n['depth_error'], '.2e')} | {fmt(n['normal_deg'], '.2f')} | {fmt(n['psnr_mask'], '.2f')} | "
                     f"{fmt(n['ssim_mask'], '.4f')} | {rl['psnr_h']:.2f} | {rl['psnr_l']:.2f} | {rl['ssim']:.4f} | "
                     f"{r['seconds_per_iteration']:.2f} |")
    return lines


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "benchmarks")
    ap.add_argument("--work", type=Path, default=ROOT / "runs" / "bench_capture_scores")
    ap.add_argument("--datasets", type=Path, default=ROOT / "runs" / "bench_pose_refinement" / "datasets",
                    help="where pose_refinement.py's datasets are (made there when missing)")
    ap.add_argument("--meshes", nargs="+", default=list(pr.MESHES), choices=pr.MESHES)
    ap.add_argument("--albedos", nargs="+", default=list(ALBEDOS), choices=ALBEDOS)
    ap.add_argument("--lights", nargs="+", default=list(LIGHTS), choices=LIGHTS)
    ap.add_argument("--iterations", type=int, default=150)
    ap.add_argument("--views", type=int, default=24)
    ap.add_argument("--holdout", type=int, default=8)
    ap.add_argument("--size", type=int, default=96)
    ap.add_argument("--spp", type=int, default=256)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    args.work.mkdir(parents=True, exist_ok=True)
    sun = sun_map(args.work / "sun.exr")
    reference_s = reference_loop_seconds()
    results = []
    t0 = time.perf_counter()
    for mesh in args.meshes:
        dataset = args.datasets / mesh
        info = pr.make_dataset(dataset, mesh, args)
        relight = relight_split(dataset, mesh, info, sun, args)
        for albedo in args.albedos:
            for light in args.lights:
                results.append(run(mesh, albedo, light, dataset, relight, sun, args))
                write(args, results, reference_s, time.perf_counter() - t0)


def write(args, results: list, reference_s: float, seconds: float):
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "capture_scores.json").write_text(json.dumps(
        {"iterations": args.iterations, "reference_loop_seconds": reference_s, "seconds": seconds,
         "results": results}, indent=1))
    text = ["# Captures scored as the field scores them", "",
            f"`benchmarks/capture_scores.py`: {args.iterations} iterations, 96² views (24 training, 4 held out), "
            f"relighting split of {RELIGHT_VIEWS} views under a sun-and-sky map, 2 CPU cores "
            f"(a 10⁷-step Python loop: {reference_s:.2f} s). See the script's docstring for the setup.", ""]
    (args.out / "capture_scores.md").write_text("\n".join(text + table(results)) + "\n")


if __name__ == "__main__":
    main()
