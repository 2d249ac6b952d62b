#!/usr/bin/env python
"""Equal-time benchmark of guided boundary sampling (the paper's Figs. 6 and 8 as numbers).

For two scenes (``configs/benchmarks/``):

- ``glossy_bunny_sky``: glossy bunny under a sky with a sun, rotated about z;
- ``soft_shadow``: bunny casting a soft shadow under a large area light, translated in x;

the boundary-only (direct term) gradient image of view 0 is estimated with every combination of
guiding {none, grid, kdtree} × sampling {light, dir, mis} × edge sorting {off, on} (sorting is
meaningless without a guide, so ``none`` runs unsorted only). Each trial gets the same wall-clock
budget: the guides are built first (their time counts) and passes of ``boundary_spp`` samples
per pixel are rendered until the budget is spent. Error: relMSE = Σ(g − ref)² / Σ ref² against
a high-sample unguided MIS reference, scaled by (time used / budget) to the exact budget (the
error is variance-dominated, variance ∝ 1/time), averaged over ``--trials`` trials with
distinct seeds.

Also recorded per guided configuration: leaves, memory, build seconds, and the ratio of build
time to the boundary render time of one iteration (one pass of ``boundary_spp``).

Outputs (atomic, refreshed after every scene): ``docs/benchmarks/guiding.json``,
``docs/benchmarks/guiding.md`` and ``docs/benchmarks/guiding_<scene>.png`` (image grid).

    .venv/bin/python benchmarks/guiding.py            # full run (≈ 10 min on 2 idle cores)
    .venv/bin/python benchmarks/guiding.py --quick    # smoke run (≈ 2 min)
"""
from __future__ import annotations

import argparse
import datetime
import platform
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import psdr_cli  # noqa: E402,F401  (configures Dr.Jit / LLVM before drjit is imported)

SCENES = ("glossy_bunny_sky", "soft_shadow")
SAMPLINGS = ("light", "dir", "mis")
CONFIGS = [("none", s, False) for s in SAMPLINGS] + [(g, s, o) for g in ("grid", "kdtree")
                                                     for o in (False, True) for s in SAMPLINGS]


def label(guiding, sampling, sort):
    return f"{guiding}/{sampling}" + ("/sorted" if sort else "")


def rel_mse(g, ref):
    return float(((g - ref) ** 2).sum() / max((ref ** 2).sum(), 1e-30))


class Bench:
    """One scene: the parsed experiment, its Mitsuba scene and the edge lists (unsorted, sorted)."""

    def __init__(self, name):
        from psdr_cli import api
        from psdr_cli.config import load_experiment
        from psdr_cli.estimators.boundary_sampling import BoundaryEdges
        self.exp = load_experiment(REPO / "configs" / "benchmarks" / f"{name}.yaml")
        self.scene, self.parameter, _, _ = api.prepare_gradient(self.exp)
        self.edges = {s: BoundaryEdges.from_scene(self.scene, sort=s) for s in (False, True)}
        self.name = name

    def settings(self, guiding, sampling, sort, seed):
        from psdr_cli import api
        from psdr_cli.gradient import Settings
        exp = api.with_estimator(self.exp, guiding=guiding, sampling=sampling, edge_sort=sort)
        st = Settings.from_experiment(exp)
        st.seed = seed
        return st

    def passes(self, st, sort, n, guides):
        """Mean direct-term image over n passes and the seconds they took."""
        from psdr_cli.gradient import forward_gradient
        st.passes = n
        st_spp = st.boundary_spp
        st.boundary_spp = st_spp * n
        est = forward_gradient(self.scene, self.edges[sort], self.parameter, 0, "direct", st, n, guides=guides)
        st.boundary_spp = st_spp
        return est.gradient, est.seconds

    def guides(self, st, sort):
        from psdr_cli.gradient import make_guides
        t0 = time.perf_counter()
        g = make_guides(self.scene, self.edges[sort], [0], ("direct",), st)
        return g, time.perf_counter() - t0

    def trial(self, guiding, sampling, sort, seed, budget):
        """One equal-time trial: (image, seconds used, guide seconds, passes, guides)."""
        st = self.settings(guiding, sampling, sort, seed)
        t0 = time.perf_counter()
        guides, build = self.guides(st, sort)
        images, n = [], 0
        while True:
            img, _ = self.passes(self.settings(guiding, sampling, sort, seed * 1000 + n), sort, 1, guides)
            images.append(img)
            n += 1
            if time.perf_counter() - t0 >= budget:
                break
        return np.mean(images, axis=0), time.perf_counter() - t0, build, n, guides


def run_scene(name, args, log):
    b = Bench(name)
    log(f"[{name}] reference: unguided MIS, {args.ref_passes} passes")
    st = b.settings("none", "mis", False, 99)
    from psdr_cli.gradient import forward_gradient
    st.passes, st.boundary_spp = args.ref_passes, st.boundary_spp * args.ref_passes
    est = forward_gradient(b.scene, b.edges[False], b.parameter, 0, "direct", st, args.ref_passes)
    ref, ref_s = est.gradient, est.seconds
    # the reference's own error, E Σ(ref − truth)² / Σref², is subtracted from every relMSE
    ref_noise = float(np.var(est.passes, axis=0, ddof=1).sum() / args.ref_passes / max((ref ** 2).sum(), 1e-30))
    log(f"[{name}]   {ref_s:.1f} s, reference relMSE ≈ {ref_noise:.2g}")
    rows, images = [], {}
    for guiding, sampling, sort in CONFIGS:
        lab = label(guiding, sampling, sort)
        b.trial(guiding, sampling, sort, 7, 0.0)  # warm-up: compile kernels
        # iteration cost: one pass without guides build (the render alone) for the build ratio
        st = b.settings(guiding, sampling, sort, 5)
        guides, build = b.guides(st, sort)
        _, pass_s = b.passes(st, sort, 1, guides)
        errs, used, builds, npasses = [], [], [], []
        for t in range(args.trials):
            img, secs, bs, n, _ = b.trial(guiding, sampling, sort, 11 + t, args.budget)
            errs.append((rel_mse(img, ref) - ref_noise) * secs / args.budget)
            used.append(secs), builds.append(bs), npasses.append(n)
            if t == 0:
                images[lab] = img
        stats = {k: {"leaves": g.stats.leaves, "max_depth": g.stats.max_depth, "memory_bytes": g.stats.memory_bytes,
                     "evaluations": g.stats.evaluations} for k, g in guides.all()}
        row = {"config": lab, "guiding": guiding, "sampling": sampling, "edge_sort": sort,
               "rel_mse": float(np.mean(errs)), "rel_mse_trials": errs, "seconds": used, "passes": npasses,
               "build_seconds": float(np.mean(builds)), "pass_seconds": pass_s,
               "build_over_iteration": float(np.mean(builds)) / pass_s if guiding != "none" else 0.0,
               "guides": stats}
        rows.append(row)
        log(f"[{name}] {lab:22s} relMSE {row['rel_mse']:.4g}  passes {npasses}  build {row['build_seconds']:.2f}s "
            f"(×{row['build_over_iteration']:.2f} of a pass)")
    return {"scene": name, "reference_passes": args.ref_passes, "reference_seconds": ref_s,
            "reference_rel_mse": ref_noise,
            "boundary_spp": b.exp.estimator.boundary_spp, "resolution": list(b.scene.resolution),
            "rows": rows}, images, ref


def markdown(results, args):
    out = ["# Guided boundary sampling: equal-time error", "",
           f"Generated by `benchmarks/guiding.py` on {results['date']} ({results['machine']}, "
           f"{results['variant']}); budget {args.budget} s per trial, {args.trials} trials. relMSE = "
           "Σ(g − ref)²/Σref² of the direct-term gradient image against a high-sample unguided MIS "
           "reference (its own estimated error subtracted), scaled to the exact budget. Guides: grid "
           "64×8×8 with 64 samples per cell and Kd-tree with 2¹⁸ first-level samples (equal target "
           "evaluations at the start), ε = 0.05. Lower is better; ‘vs grid’ divides by the grid "
           "guide's error with the same sampling and sorting.", ""]
    for sc in results["scenes"]:
        rows = {r["config"]: r for r in sc["rows"]}
        out += [f"## {sc['scene']} ({sc['resolution'][0]}×{sc['resolution'][1]}, {sc['boundary_spp']} spp per pass)", "",
                "| guiding | sampling | sorted | relMSE | vs none | vs grid | passes | leaves | memory | build s | build / pass |",
                "|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
        for r in sc["rows"]:
            none = rows[label("none", r["sampling"], False)]["rel_mse"]
            grid = rows.get(label("grid", r["sampling"], r["edge_sort"]))
            vs_grid = f"{r['rel_mse'] / grid['rel_mse']:.2f}" if grid and r["guiding"] != "none" else "—"
            leaves = sum(g["leaves"] for g in r["guides"].values())
            mem = sum(g["memory_bytes"] for g in r["guides"].values())
            out.append(f"| {r['guiding']} | {r['sampling']} | {'yes' if r['edge_sort'] else 'no'} | "
                       f"{r['rel_mse']:.4g} | {r['rel_mse'] / none:.2f} | {vs_grid} | {int(np.mean(r['passes']))} | "
                       f"{leaves or '—'} | {f'{mem / 1024:.0f} KiB' if mem else '—'} | "
                       f"{r['build_seconds']:.2f} | {r['build_over_iteration']:.2f} |")
        out += ["", f"![{sc['scene']}](guiding_{sc['scene']}.png)", ""]
    return "\n".join(out) + "\n"


def image_grid(path, name, images, ref, rows):
    from psdr_cli import plots
    import matplotlib.pyplot as plt
    err = {r["config"]: r["rel_mse"] for r in rows}
    cols = [(s, o) for o in (False, True) for s in SAMPLINGS]
    fig, axes = plt.subplots(4, 6, figsize=(13, 9))
    scale = float(np.percentile(np.abs(ref.sum(-1)), 99)) or 1.0
    for ax in axes.ravel():
        ax.axis("off")
    axes[0, 0].imshow(ref.sum(-1), cmap="RdBu_r", vmin=-scale, vmax=scale)
    axes[0, 0].set_title("reference", fontsize=8)
    for i, guiding in enumerate(("none", "grid", "kdtree")):
        for j, (s, o) in enumerate(cols):
            lab = label(guiding, s, o)
            if lab not in images:
                continue
            ax = axes[i + 1, j]
            ax.imshow(images[lab].sum(-1), cmap="RdBu_r", vmin=-scale, vmax=scale)
            ax.set_title(f"{lab}\nrelMSE {err[lab]:.3g}", fontsize=7)
    fig.suptitle(f"{name}: direct-term gradient at equal time")
    plots.save(fig, path)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--budget", type=float, default=6.0, help="seconds per trial (default 6)")
    ap.add_argument("--trials", type=int, default=2)
    ap.add_argument("--ref-passes", type=int, default=1024, help="passes of the unguided MIS reference")
    ap.add_argument("--scenes", default=",".join(SCENES))
    ap.add_argument("--quick", action="store_true", help="smoke run: 1 trial, 1.5 s budget, 32 reference passes")
    ap.add_argument("--out", type=Path, default=REPO / "docs" / "benchmarks")
    args = ap.parse_args()
    if args.quick:
        args.budget, args.trials, args.ref_passes = 1.5, 1, 32
    from psdr_cli import api, io
    from psdr_cli.config import load_experiment
    variant = api.setup(load_experiment(REPO / "configs" / "benchmarks" / f"{SCENES[0]}.yaml"))
    results = {"date": datetime.date.today().isoformat(), "machine": f"{platform.machine()}, {__import__('os').cpu_count()} cores",
               "variant": variant, "budget_seconds": args.budget, "trials": args.trials, "scenes": []}
    t0 = time.perf_counter()
    for name in args.scenes.split(","):
        res, images, ref = run_scene(name, args, lambda m: print(m, flush=True))
        results["scenes"].append(res)
        image_grid(args.out / f"guiding_{name}.png", name, images, ref, res["rows"])
        io.write_json(args.out / "guiding.json", results)
        with io.atomic_path(args.out / "guiding.md") as tmp:
            Path(tmp).write_text(markdown(results, args))
    print(f"done in {time.perf_counter() - t0:.0f} s → {args.out}/guiding.md")


if __name__ == "__main__":
    main()
