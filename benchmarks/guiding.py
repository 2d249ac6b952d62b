#!/usr/bin/env python
"""Equal-time benchmark of guided boundary sampling (the paper's Figs. 6 and 8 as numbers).

For the three Fig. 6 scenes (``configs/benchmarks/``), each at its own resolution or at
``name@N`` (N × N pixels):

- ``glossy_bunny_sky``: glossy bunny under a sky with a sun, rotated about z (direct term);
- ``soft_shadow``: bunny casting a soft shadow under a large area light, translated in x (direct);
- ``cornell_glass``: Cornell box with a rough-glass sphere, translated (direct + indirect terms);

the boundary gradient image of view 0 is estimated with every combination of guiding {none,
grid, kdtree} × sampling {light, dir, mis} × edge sorting {off, on} (sorting is meaningless
without a guide, so ``none`` runs unsorted only), plus ``auto/mis`` (the default: what
:mod:`psdr_cli.guiding.auto` picks for the size); ``--configs`` selects a subset. Each trial gets
the same wall-clock budget: the guides are built first (their time counts) and passes of
``boundary_spp`` samples per pixel are rendered until the budget is spent. The configurations
run interleaved (trial t of every configuration before trial t + 1), so a change in machine
load affects all of them alike. Error: relMSE = Σ(g − ref)² / Σ ref² against a high-sample
unguided MIS reference (its own estimated error subtracted), scaled by (time used / budget) to
the exact budget (the error is variance-dominated, variance ∝ 1/time), averaged over
``--trials`` trials with distinct seeds.

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
import json
import platform
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import psdr_cli  # noqa: E402  (configures Dr.Jit / LLVM before drjit is imported)
from psdr_cli.commands.compare import Comparison, rel_mse  # noqa: E402
from psdr_cli.config.variants_section import Variant  # noqa: E402
from psdr_cli.config.vocabularies import SAMPLINGS  # noqa: E402
from psdr_cli.experiment.load import load_experiment  # noqa: E402
from psdr_cli.support import fileio, plots  # noqa: E402

SCENES = ("glossy_bunny_sky", "soft_shadow", "cornell_glass")
CONFIGS = [("none", s, False) for s in SAMPLINGS] + [(g, s, o) for g in ("grid", "kdtree")
                                                     for o in (False, True) for s in SAMPLINGS] + [("auto", "mis", False)]


def label(guiding, sampling, sort):
    return f"{guiding}/{sampling}" + ("/sorted" if sort else "")


def scene_experiment(spec):
    """(label, experiment) of ``name`` or ``name@N`` (film N × N)."""
    name, _, res = spec.partition("@")
    exp = load_experiment(REPO / "configs" / "benchmarks" / f"{name}.yaml")
    if res:
        exp = replace(exp, scene=replace(exp.scene, width=int(res), height=int(res)))
    return spec, exp


def run_scene(spec, args, log):
    name, exp = scene_experiment(spec)
    b = Comparison(exp, exp.estimator.terms)
    pixels = exp.scene.width * exp.scene.height
    ref_passes = max(min(64, args.ref_passes), min(args.ref_passes, args.ref_passes * 48 * 48 // pixels))
    log(f"[{name}] reference: unguided MIS, {ref_passes} passes")
    ref, ref_noise, ref_s = b.reference(ref_passes)
    log(f"[{name}]   {ref_s:.1f} s, reference relMSE ≈ {ref_noise:.2g}")
    configs = [c for c in CONFIGS if not args.configs or label(*c) in args.configs.split(",")]
    variants = [Variant(label(*c), guiding=c[0], sampling=c[1], edge_sort=c[2]) for c in configs]
    pass_seconds = {}
    for v in variants:  # warm-up (kernel compilation), then one timed pass
        b.trial(replace(v, passes=1), 7, 0.0)
        guides, _ = b.guides(v, 5)
        pass_seconds[v.label] = b.passes(v, 5, 1, guides)[2]
    trials = {v.label: [] for v in variants}
    for t in range(args.trials):  # interleaved: trial t of every configuration, then t + 1
        for v in variants:
            trials[v.label].append(b.trial(v, 11 + t, args.budget))
    rows, images = [], {}
    for (guiding, sampling, sort), v in zip(configs, variants):
        runs = trials[v.label]
        errs = [(rel_mse(img, ref) - ref_noise) * secs / args.budget for img, secs, _, _, _ in runs]
        guides = runs[-1][4]
        images[v.label] = runs[0][0]
        build = float(np.mean([r[2] for r in runs]))
        chosen = sorted({g.kind for _, g in guides.all()}) or ["none"]
        row = {"config": v.label, "guiding": guiding, "sampling": sampling, "edge_sort": sort,
               "chosen": "+".join(chosen), "rel_mse": float(np.mean(errs)), "rel_mse_trials": errs,
               "seconds": [r[1] for r in runs], "passes": [r[3] for r in runs], "build_seconds": build,
               "pass_seconds": pass_seconds[v.label],
               "build_over_iteration": build / pass_seconds[v.label] if guides.all() else 0.0,
               "guides": {k: {"leaves": g.stats.leaves, "max_depth": g.stats.max_depth,
                              "memory_bytes": g.stats.memory_bytes, "evaluations": g.stats.evaluations}
                          for k, g in guides.all()}}
        rows.append(row)
        log(f"[{name}] {v.label:22s} relMSE {row['rel_mse']:.4g}  passes {row['passes']}  build {build:.2f}s "
            f"(×{row['build_over_iteration']:.2f} of a pass)")
    return {"scene": name, "terms": list(exp.estimator.terms), "reference_passes": ref_passes,
            "reference_seconds": ref_s, "reference_rel_mse": ref_noise,
            "boundary_spp": exp.estimator.boundary_spp, "resolution": list(b.scene.resolution),
            "rows": rows}, images, ref


def markdown(results, args):
    out = ["# Guided boundary sampling: equal-time error", "",
           f"Generated by `benchmarks/guiding.py` on {results['date']} ({results['machine']}, "
           f"{results['variant']}; {args.note}); budget {args.budget} s per trial, {args.trials} trials, "
           "configurations interleaved. relMSE = Σ(g − ref)²/Σref² of the boundary gradient image (the "
           "scene's boundary terms) against a high-sample unguided MIS reference (its own estimated "
           "error subtracted), scaled to the exact budget; build time counts. Guides: grid 64×8×8 with "
           "64 samples per cell; Kd-tree from one batch of target samples (half the lanes of one pass, "
           "within [2¹⁷, 2¹⁸]), MIS guides sharing their edge profile; forward-mode targets include the "
           "velocity; ε = 0.05. `auto` is the default (`estimator.guiding: auto`, docs/config.md); "
           "‘chosen’ says what it picked when the row ran. Lower is better; ‘vs none’ divides by unguided with the same "
           "sampling, ‘vs grid’ by the grid guide's error with the same sampling and sorting.", ""]
    for sc in results["scenes"]:
        rows = {r["config"]: r for r in sc["rows"]}
        out += [f"## {sc['scene']} ({sc['resolution'][0]}×{sc['resolution'][1]}, {sc['boundary_spp']} spp per pass, "
                f"{' + '.join(sc.get('terms', ['direct']))})", "",
                "| guiding | sampling | sorted | chosen | relMSE | vs none | vs grid | passes | leaves | memory | build s | build / pass |",
                "|---|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
        for r in sc["rows"]:
            none = rows.get(label("none", r["sampling"], False))
            grid = rows.get(label("grid", r["sampling"], r["edge_sort"]))
            vs_none = f"{r['rel_mse'] / none['rel_mse']:.2f}" if none else "—"
            vs_grid = f"{r['rel_mse'] / grid['rel_mse']:.2f}" if grid and r["guiding"] != "none" else "—"
            leaves = sum(g["leaves"] for g in r["guides"].values())
            mem = sum(g["memory_bytes"] for g in r["guides"].values())
            out.append(f"| {r['guiding']} | {r['sampling']} | {'yes' if r['edge_sort'] else 'no'} | {r.get('chosen', '')} | "
                       f"{r['rel_mse']:.4g} | {vs_none} | {vs_grid} | {int(np.mean(r['passes']))} | "
                       f"{leaves or '—'} | {f'{mem / 1024:.0f} KiB' if mem else '—'} | "
                       f"{r['build_seconds']:.2f} | {r['build_over_iteration']:.2f} |")
        out += ["", f"![{sc['scene']}](guiding_{sc['scene']}.png)", ""]
    return "\n".join(out) + "\n"


#: hand-written notes below this line of guiding.md survive a regeneration of the tables
NOTES = "<!-- notes: kept when the tables are regenerated -->"


def write_markdown(path: Path, text: str):
    """Write the tables, keeping the notes section of the existing file (from NOTES on)."""
    old = path.read_text() if path.exists() else ""
    notes = old[old.index(NOTES):] if NOTES in old else ""
    with fileio.atomic_path(path) as tmp:
        Path(tmp).write_text(text + ("\n" + notes if notes else ""))


def image_grid(path, name, images, ref, rows):
    err = {r["config"]: r["rel_mse"] for r in rows}
    cols = [(s, o) for o in (False, True) for s in SAMPLINGS]
    plt = plots.pyplot()
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
    ap.add_argument("--ref-passes", type=int, default=1024,
                    help="passes of the unguided MIS reference at 48² (scaled by 48²/pixels, at least 64)")
    ap.add_argument("--scenes", default=",".join(SCENES + tuple(f"{n}@128" for n in SCENES)),
                    help="scenes, name or name@N for N × N pixels (default: the three at their size and at 128²)")
    ap.add_argument("--configs", default="", help="comma-separated configurations, e.g. none/mis,kdtree/mis (default: all)")
    ap.add_argument("--quick", action="store_true", help="smoke run: 1 trial, 1.5 s budget, 32 reference passes")
    ap.add_argument("--out", type=Path, default=REPO / "docs" / "benchmarks")
    ap.add_argument("--note", default="idle machine", help="machine state written to the table header")
    ap.add_argument("--update", action="store_true",
                    help="keep the other scenes of the existing guiding.json (re-run only --scenes)")
    args = ap.parse_args()
    if args.quick:
        args.budget, args.trials, args.ref_passes = 1.5, 1, 32
    variant = psdr_cli.setup(load_experiment(REPO / "configs" / "benchmarks" / f"{SCENES[0]}.yaml"))
    results = {"date": datetime.date.today().isoformat(), "machine": f"{platform.machine()}, {__import__('os').cpu_count()} cores",
               "variant": variant, "budget_seconds": args.budget, "trials": args.trials, "scenes": []}
    old = json.loads((args.out / "guiding.json").read_text()) if args.update and (args.out / "guiding.json").exists() else None
    order = [s["scene"] for s in old["scenes"]] if old else []
    t0 = time.perf_counter()
    for name in args.scenes.split(","):
        res, images, ref = run_scene(name, args, lambda m: print(m, flush=True))
        results["scenes"].append(res)
        if old:  # the other scenes as they were, in their old order
            done = {s["scene"]: s for s in results["scenes"]}
            kept = [done.get(n, s) for n, s in zip(order, old["scenes"])]
            results["scenes"] = kept + [s for s in results["scenes"] if s["scene"] not in order]
        image_grid(args.out / f"guiding_{name}.png", name, images, ref, res["rows"])
        fileio.write_json(args.out / "guiding.json", results)
        write_markdown(args.out / "guiding.md", markdown(results, args))
    print(f"done in {time.perf_counter() - t0:.0f} s → {args.out}/guiding.md")


if __name__ == "__main__":
    main()
