#!/usr/bin/env python
"""What the photographs can tell about a camera's pose when everything else is exact: a pose-only
fit of each view with the true scene, at several image sizes.

The joint runs of ``pose_refinement.py`` bring the reprojection error down 3–5× but the rotation
and the centre error taken apart only 1.0–2.1× and 0.6–1.1×. A turn of the camera across the image
by θ and a sideways shift by θ·d (d the distance to the object) move the object's image alike;
only the parallax between its near and far parts (about f θ · 2r/d pixels for an object of radius
r at focal length f) tells them apart. This benchmark asks how much of that split an image of a
given size carries, with nothing else unknown:

1. **Datasets.** ``pose_refinement.make_dataset`` (Mitsuba's own ``path`` integrator, the
   textured principled object under ``scenes/studio.exr``) at each size of ``--sizes``, ``--views``
   training views, every pose perturbed by ``--level`` degrees and ``--level``/100 of its distance
   (``pose_refinement.perturbed_copy``: the joint benchmark's draws per camera index; with
   another ``--views`` the cameras themselves are placed differently).
2. **Fit.** The true mesh with its true albedo (the per-vertex colours the dataset was rendered
   with) and roughness under the experiment's light, rendered as the joint runs render (their
   experiment's ``scene.max_depth`` 2, against photographs rendered at depth 3: the one modelling
   difference left); every training view's pose correction is
   fitted alone to its photograph (``psdr_cli.scoring.held_out_alignment.align_views``, the
   fit ``psdr evaluate`` aligns held-out views with: no gauge, the fixed scene pins each pose),
   for ``--fit-iterations`` Adam steps (the first ``--fit-views`` training views, or all).
3. **Scores.** Per view, against the true camera (no alignment: the scene is the truth): the
   rotation error (degrees), the centre error (a fraction of the camera's distance to the
   look-at point) and the reprojection error (pixels at that size, the true mesh's vertices),
   before and after; their medians over the views and the falls (before / after).

Outputs ``<out>/pose_observability.json`` and ``.md`` (with the machine's 10⁷-step loop time).
``--bound`` prints instead what a split without any parallax allows (:func:`split_bound`).

    .venv/bin/python benchmarks/pose_observability.py --sizes 96 192 384 --views 8
    .venv/bin/python benchmarks/pose_observability.py --bound --level 0.5
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import pose_refinement as bench  # noqa: E402
from machine import reference_loop_seconds  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def true_scene(exp, V_dataset: np.ndarray, F: np.ndarray, colours: np.ndarray):
    """The psdr scene of ``exp`` (the dataset's training cameras as given) with the true mesh and
    its true material: a principled BSDF whose base colour is the per-vertex ``colours``."""
    import mitsuba as mi
    from psdr_cli.experiment.dataset_frame import to_normalised
    from psdr_cli.scene import build

    plain = build.mitsuba_mesh

    def textured(name, V, F_, bsdf, smooth=False, uv=None):
        bsdf = {"type": "principled", "roughness": bench.ROUGHNESS,
                "base_color": {"type": "mesh_attribute", "name": "vertex_color"}}
        mesh = plain(name, V, F_, bsdf, smooth, uv)
        mesh.add_attribute("vertex_color", 3, mi.Float(np.ravel(colours).astype(np.float32)))
        return mesh

    build.mitsuba_mesh = textured
    try:
        V = to_normalised(V_dataset, exp.optimize.target_dataset.frame)
        return build.build_scene(exp, objects={exp.optimize.object: (V, F)})
    finally:
        build.mitsuba_mesh = plain


def view_errors(true: np.ndarray, estimated: np.ndarray, look_at, points, focal: float) -> list:
    """[rotation °, centre error / distance, reprojection px] of one camera (OpenCV
    camera-to-world) against the truth."""
    distance = float(np.linalg.norm(true[:3, 3] - np.asarray(look_at)))
    return [bench.angle_deg(true[:3, :3] @ estimated[:3, :3].T),
            float(np.linalg.norm(true[:3, 3] - estimated[:3, 3])) / distance,
            bench.reprojection(true, estimated, points, focal)]


def fit_size(size: int, args, work: Path) -> dict:
    """Render (or reuse) the dataset at ``size``², perturb it, fit every training view with the
    true scene and score it (module docstring)."""
    import mitsuba as mi
    mi.set_variant("llvm_ad_rgb")
    from psdr_cli.experiment.dataset_frame import dataset_frames, dataset_scene
    from psdr_cli.experiment.load import load_experiment
    from psdr_cli.run_folder.refined_cameras import refined_poses
    from psdr_cli.scoring.held_out_alignment import align_views
    from psdr_cli.target_sources.camera_dataset import dataset_views, target_image

    ns = argparse.Namespace(views=args.views, holdout=args.holdout, size=size, spp=args.spp, seed=args.seed)
    folder = work / "datasets" / f"{args.mesh}_{size}"
    info = bench.make_dataset(folder, args.mesh, ns)
    dataset = bench.perturbed_copy(folder, args.level, info["look_at"], args.seed)
    truth = json.loads((dataset / "true_poses.json").read_text())
    cfg = bench.experiment(work / "configs" / f"{args.mesh}_{size}.yaml", f"{args.mesh}_{size}", dataset,
                           work / "runs", "off", 1)
    exp = dataset_scene(load_experiment(cfg), split="train")
    exp.scene.max_depth = args.fit_depth
    V, F = bench.load_mesh(args.mesh)
    scene = true_scene(exp, V, F, bench.patch_colours(V, args.seed + 17))
    views = dataset_views(exp)
    targets = [target_image(view, exp.scene.hide_background) for view in views][:args.fit_views]
    frames = dataset_frames(exp.optimize.target_dataset, "train")[1][:args.fit_views]
    t = time.perf_counter()
    cams = align_views(scene, exp, targets, iterations=args.fit_iterations)
    seconds = time.perf_counter() - t
    fitted = refined_poses([f.cam_to_world for f in frames], cams.initial, cams.matrices(),
                           exp.optimize.target_dataset.frame)
    estimated = bench.match_names({bench.frame_name(f.name): M for f, M in zip(frames, fitted)}, truth)
    by_name = {v["name"]: v for v in truth["views"]}
    points = bench.object_points(folder / "ground_truth.ply")
    focal = size / (2 * math.tan(math.radians(bench.FOV) / 2))
    rows = []
    for name, after in estimated.items():
        true, given = np.asarray(by_name[name]["true"]), np.asarray(by_name[name]["given"])
        rows.append({"name": name, "before": view_errors(true, given, truth["look_at"], points, focal),
                     "after": view_errors(true, after, truth["look_at"], points, focal)})
    return {"size": size, "views": len(rows), "fit_seconds": seconds, "per_view": rows,
            "median_before": np.median([r["before"] for r in rows], 0).tolist(),
            "median_after": np.median([r["after"] for r in rows], 0).tolist(),
            "parallax_px_per_degree": parallax(points, truth, focal)}


def parallax(points: np.ndarray, truth: dict, focal: float) -> float:
    """The median over training views of the parallax (pixels) between a camera turned by 1°
    across the image and the same camera shifted sideways by as much at the look-at point: the
    part of the image that tells the two apart."""
    out = []
    for v in truth["views"]:
        if v["split"] != "train":
            continue
        M = np.asarray(v["true"], np.float64)
        d = float(np.linalg.norm(M[:3, 3] - np.asarray(truth["look_at"])))
        a = math.radians(1.0)
        turned = M.copy()
        turned[:3, :3] = M[:3, :3] @ bench.rotation([0, 1, 0], 1.0)        # pan about the camera's y
        shifted = M.copy()
        shifted[:3, 3] = M[:3, 3] + M[:3, 0] * d * a                      # along the camera's x
        out.append(bench.reprojection(turned, shifted, points, focal))
    return float(np.median(out))


def split_bound(level: float, draws: int = 200_000, seed: int = 0) -> dict:
    """The falls (before / after, medians) of the rotation and translation errors when an image
    pins only each camera's roll and the sums pan + sideways x and tilt + sideways y (no parallax),
    for the benchmark's draws (a turn of ``level``° about a random axis, a move of ``level`` % of
    the distance in a random direction): split in proportion to the two parts' prior variances
    (the least-squares split), or wholly to the turn; the distance along the axis unknown or known."""
    rng = np.random.default_rng(seed)

    def directions():
        v = rng.normal(size=(draws, 3))
        return v / np.linalg.norm(v, axis=1, keepdims=True)

    r, t = directions() * math.radians(level), directions() * level / 100
    sums = np.stack([r[:, 1] + t[:, 0], -r[:, 0] + t[:, 1]], 1)
    share_prior = (math.radians(level) ** 2) / (math.radians(level) ** 2 + (level / 100) ** 2)
    out = {}
    for name, share in (("prior", share_prior), ("turn", 1.0)):
        for known_depth in (False, True):
            r_hat, t_hat = np.zeros_like(r), np.zeros_like(t)
            r_hat[:, 1], r_hat[:, 0], r_hat[:, 2] = share * sums[:, 0], -share * sums[:, 1], r[:, 2]
            t_hat[:, 0], t_hat[:, 1] = (1 - share) * sums[:, 0], (1 - share) * sums[:, 1]
            if known_depth:
                t_hat[:, 2] = t[:, 2]
            before_r, before_t = np.median(np.linalg.norm(r, axis=1)), np.median(np.linalg.norm(t, axis=1))
            out[f"{name}{'_depth_known' if known_depth else ''}"] = {
                "turn_share": share,
                "rotation_fall": float(before_r / np.median(np.linalg.norm(r - r_hat, axis=1))),
                "translation_fall": float(before_t / np.median(np.linalg.norm(t - t_hat, axis=1)))}
    return out


def write_report(args, results: list, reference_s: float):
    data = {"mesh": args.mesh, "level_deg": args.level, "views": args.views, "fit_iterations": args.fit_iterations,
            "fit_depth": args.fit_depth,
            "reference_loop_seconds": reference_s, "results": results}
    (args.out / "pose_observability.json").write_text(json.dumps(data, indent=1))
    lines = ["# What a photograph says about its camera's pose (benchmarks/pose_observability.py)", "",
             f"The {args.mesh} of `pose_refinement.py` (Mitsuba `path`, textured principled, `scenes/studio.exr`), "
             f"{args.views} training views (the first {args.fit_views or args.views} fitted), every pose turned by {args.level}° about a random axis and moved by "
             f"{args.level / 100:.1%} of its distance (the joint benchmark's draws). Each view's pose fitted alone "
             f"({args.fit_iterations} Adam steps, `psdr evaluate`'s held-out alignment) with the **true** mesh, "
             f"albedo, roughness and light (rendered with {args.fit_depth} path segments, the photographs with 3). "
             f"Errors against the true camera, medians over the views; reference "
             f"10⁷-step Python loop: {reference_s:.2f} s.", "",
             "| size | rotation ° before → after (fall) | centre % before → after (fall) | "
             "reprojection px before → after (fall) | parallax px of 1° turn vs shift | fit s |",
             "|---:|---|---|---|---:|---:|"]
    for r in results:
        b, a = r["median_before"], r["median_after"]
        cell = lambda k, s=1.0: f"{b[k] * s:.3f} → {a[k] * s:.3f} (÷{b[k] / max(a[k], 1e-12):.1f})"  # noqa: E731
        lines.append(f"| {r['size']}² | {cell(0)} | {cell(1, 100)} | {cell(2)} | {r['parallax_px_per_degree']:.2f} "
                     f"| {r['fit_seconds']:.0f} |")
    (args.out / "pose_observability.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "benchmarks")
    ap.add_argument("--work", type=Path, default=ROOT / "runs" / "bench_pose_observability")
    ap.add_argument("--mesh", default="bunny", choices=bench.MESHES)
    ap.add_argument("--sizes", nargs="+", type=int, default=[96, 192, 384])
    ap.add_argument("--level", type=float, default=0.5)
    ap.add_argument("--views", type=int, default=8, help="training views (every --holdout-th camera is held out)")
    ap.add_argument("--holdout", type=int, default=8)
    ap.add_argument("--spp", type=int, default=256, help="samples per pixel of the dataset renders")
    ap.add_argument("--fit-iterations", type=int, default=100)
    ap.add_argument("--fit-views", type=int, default=None, help="fit only the first K training views (default: all)")
    ap.add_argument("--fit-depth", type=int, default=2,
                    help="path segments of the fit's renders (the joint runs' 2; the photographs have 3)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--bound", action="store_true",
                    help="only the falls a split without parallax allows (split_bound), printed as JSON")
    args = ap.parse_args(argv)
    if args.bound:
        print(json.dumps(split_bound(args.level), indent=1))
        return
    args.out, work = args.out.resolve(), args.work.resolve()
    args.out.mkdir(parents=True, exist_ok=True)
    reference_s = reference_loop_seconds()
    results = []
    for size in args.sizes:
        results.append(fit_size(size, args, work))
        write_report(args, results, reference_s)


if __name__ == "__main__":
    main()
