#!/usr/bin/env python
"""Guided boundary sampling in the optimisation loop: every estimator at its own best step, then
the ratio Kd-tree / unguided at equal time against the scale of the problem.

Both stages run ``psdr optimize --ray`` on generated experiments: one Ray task per run, as many at
once as the machine has cores, each run with the same wall-clock budget (``optimize.seconds``), so
that runs of both estimators share the machine alike. The base is a Fig. 10 experiment
(``configs/paper/cpu/fig10_shadow.yaml`` or ``fig10_glass.yaml``) with its variants replaced:

1. **Step sweep** (each estimator at its best step). Unguided MIS and the loop-fed Kd-tree
   (``guiding: kdtree``, MIS, sorted edges) at every learning rate × LargeSteps λ of the grid, one
   seed, ``--sweep-iterations`` each (a fixed count, not a time budget: the best step does not
   depend on what else the machine runs; the remesh schedule is the experiment's). A run's score
   is the mean Chamfer-L1 of its checkpoints in the last sixth of its iterations (a single
   checkpoint jumps with the steps); each estimator's best (learning rate, λ) is the one of
   lowest score.
2. **Crossover.** At each scale, both estimators at their own best step, ``--seeds`` seeds each,
   ``--seconds`` each. Scales: boundary spp 1, 2 and 8 (the experiment's), and 8 spp at four
   times the vertices (remeshing to 4× the experiment's counts). Fewer boundary samples or more
   vertices make the unguided gradient noisier per unknown, which is where a guide can pay. The
   ratio of the seeds' mean Chamfer-L1 (Kd-tree / unguided) is reported at a third, two thirds
   and all of the time, and plotted against the scale. ``--scales "vertices ×16"`` adds 16 times
   the vertices (32 000 at the last remesh), which needs longer runs (``--seconds 300``).

Errors are normalised by the ground truth's bounding box (:func:`psdr_cli.commands.evaluate.distance`).
Outputs: ``<out>/guided_loop_<scene>.md``, ``.json``, ``.png``. Finished runs are reused.

    .venv/bin/python benchmarks/guided_loop.py --scene shadow --runs runs/benchmarks/guided_loop
"""
from __future__ import annotations

import argparse
import copy
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import yaml

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import psdr_cli  # noqa: E402,F401  (configures Dr.Jit / LLVM before drjit is imported)
from psdr_cli.commands import evaluate as ev  # noqa: E402
from psdr_cli.run_folder.layout import RunFiles  # noqa: E402
from psdr_cli.run_folder.log import read_log  # noqa: E402
from psdr_cli.support.fileio import atomic_path  # noqa: E402
from psdr_cli.support.plots import pyplot, save  # noqa: E402

BASES = {"shadow": REPO / "configs" / "paper" / "cpu" / "fig10_shadow.yaml",
         "glass": REPO / "configs" / "paper" / "cpu" / "fig10_glass.yaml"}
GUIDES = {"unguided": {"guiding": "none", "edge_sort": False}, "kdtree": {"guiding": "kdtree", "edge_sort": True}}
#: scale name -> (boundary spp or None for the experiment's, vertex factor)
SCALES = {"spp 1": (1, 1), "spp 2": (2, 1), "experiment's": (None, 1), "vertices ×4": (None, 4),
          "vertices ×16": (None, 16)}
#: 1-minute load average after each batch of runs (reported: what else shared the machine)
LOADS = []


def base_experiment(scene: str, name: str, runs: Path, seconds: float | None, iterations: int = 100_000) -> dict:
    """The Fig. 10 experiment without its variants, with a time budget (or none) and frequent
    checkpoints."""
    d = copy.deepcopy(yaml.safe_load(BASES[scene].read_text()))
    d["name"], d["output"] = name, str(runs)
    o = d["optimize"]
    o.pop("variants", None)
    o.pop("seconds", None)
    o.update(iterations=iterations, checkpoint_every=25)
    if seconds is not None:
        o["seconds"] = seconds
    return d


def scaled(d: dict, scale: str) -> dict:
    """The experiment at one of :data:`SCALES`."""
    spp, factor = SCALES[scale]
    d = copy.deepcopy(d)
    if spp is not None:
        d["estimator"]["boundary_spp"] = spp
    remesh = d["optimize"].get("remesh")
    if factor != 1 and remesh:
        remesh["initial"] = remesh["initial"] * factor
        remesh["vertices"] = [v * factor for v in remesh["vertices"]]
    return d


def variant(guide: str, lr: float, lam: float, seed: int) -> dict:
    return {"label": f"{guide}_lr{lr:g}_l{lam:g}_s{seed}", **GUIDES[guide], "learning_rate": lr, "lambda": lam,
            "seed": seed}


def run_all(data: dict, runs: Path) -> dict:
    """{label: [(iteration, seconds, Chamfer-L1)]} of every variant of ``data``, optimised as Ray
    tasks (finished runs are kept: ``--resume``) and evaluated."""
    cfg = runs / f"{data['name']}.yaml"
    cfg.write_text(yaml.safe_dump(data, sort_keys=False))
    subprocess.run([sys.executable, "-m", "psdr_cli", "optimize", str(cfg), "--ray", "--resume"], check=True,
                   cwd=REPO, stdout=subprocess.DEVNULL)
    LOADS.append(os.getloadavg()[0])
    return {v["label"]: curve(runs / data["name"] / v["label"]) for v in data["optimize"]["variants"]}


def curve(run: Path, samples: int = 50_000) -> list:
    """[(iteration, seconds, Chamfer-L1)] of every checkpoint of a finished run."""
    files = RunFiles(run)
    cached = run / "chamfer.json"
    if cached.exists():
        return [tuple(c) for c in json.loads(cached.read_text())]
    reference = ev.load(files.reference)
    seconds = {int(r["iteration"]) + 1: float(r["seconds_total"]) for r in read_log(files.log)}
    seconds[0] = 0.0
    out = [(it, seconds[it], ev.distance(ev.load(p), reference, samples).chamfer_l1)
           for p in sorted(files.checkpoints.glob("iter_*.ply"))
           for it in [int(p.stem.split("_")[1])] if it in seconds]
    cached.write_text(json.dumps(out))
    return out


def late_score(c: list) -> float:
    """Mean Chamfer-L1 of the checkpoints in the last sixth of the iterations."""
    return float(np.mean([x[2] for x in c if x[0] >= c[-1][0] * 5 / 6]))


def at_time(c: list, t: float) -> float:
    """Chamfer-L1 of the checkpoint that crossed ``t`` seconds (the last one if none did)."""
    return next((x[2] for x in c if x[1] >= t - 1e-9), c[-1][2])


def sweep(args, runs: Path) -> dict:
    """{guide: {(lr, λ): score}} of the step sweep."""
    data = base_experiment(args.scene, f"{args.scene}_sweep", runs, None, args.sweep_iterations)
    # both estimators at one step side by side: Ray runs them at the same time, under the same load
    data["optimize"]["variants"] = [variant(g, lr, lam, 0) for lr in args.lr for lam in args.lam for g in GUIDES]
    curves = run_all(data, runs)
    return {g: {(lr, lam): late_score(curves[variant(g, lr, lam, 0)["label"]])
                for lr in args.lr for lam in args.lam} for g in GUIDES}


def crossover(args, runs: Path, best: dict) -> dict:
    """{scale: {guide: [curve per seed]}} at each guide's best step."""
    out = {}
    for scale in args.scales:
        i = list(SCALES).index(scale)
        data = scaled(base_experiment(args.scene, f"{args.scene}_scale{i}", runs, args.seconds), scale)
        data["optimize"]["variants"] = [variant(g, *best[g], s) for s in args.seeds for g in GUIDES]
        curves = run_all(data, runs)
        out[scale] = {g: [curves[variant(g, *best[g], s)["label"]] for s in args.seeds] for g in GUIDES}
    return out


def ratios(cross: dict, times: list) -> dict:
    """{scale: [Kd-tree / unguided mean Chamfer-L1 at each time]}."""
    return {scale: [float(np.mean([at_time(c, t) for c in by["kdtree"]]) /
                          np.mean([at_time(c, t) for c in by["unguided"]])) for t in times]
            for scale, by in cross.items()}


def report(args, scores: dict, best: dict, cross: dict, wall: float) -> str:
    times = [args.seconds / 3, 2 * args.seconds / 3, args.seconds]
    r = ratios(cross, times)
    lines = [f"# Guided boundary sampling in the loop ({args.scene}): best steps and the crossover", "",
             f"`benchmarks/guided_loop.py {' '.join(sys.argv[1:])}` — {time.strftime('%Y-%m-%d %H:%M')}, "
             f"{platform.machine()}, {os.cpu_count()} cores, one Ray task per run (Dr.Jit threads per run: 1), "
             f"wall time {wall / 60:.1f} min; 1-minute load average after each batch of runs: "
             f"{', '.join(f'{x:.1f}' for x in LOADS)}. Chamfer-L1 normalised by the ground truth's bounding box.", "",
             f"## Step sweep ({args.sweep_iterations} iterations per run, one seed; mean Chamfer-L1 of the "
             f"checkpoints in the last sixth)", "",
             "| estimator | learning rate | " + " | ".join(f"λ {lam:g}" for lam in args.lam) + " |",
             "|---|---|" + "---|" * len(args.lam)]
    for g in GUIDES:
        for lr in args.lr:
            cells = [f"**{scores[g][(lr, lam)]:.4f}**" if (lr, lam) == best[g] else f"{scores[g][(lr, lam)]:.4f}"
                     for lam in args.lam]
            lines.append(f"| {g} | {lr:g} | " + " | ".join(cells) + " |")
    lines += ["", "Best: " + "; ".join(f"{g} lr {best[g][0]:g}, λ {best[g][1]:g}" for g in GUIDES) + ".", "",
              f"## Crossover ({args.seconds:g} s per run, seeds {', '.join(map(str, args.seeds))}, "
              "each estimator at its best step)", "",
              "| scale | " + " | ".join(f"unguided at {t:.0f} s | Kd-tree at {t:.0f} s | ratio" for t in times) + " |",
              "|---|" + "---|---|---|" * len(times)]
    for scale, by in cross.items():
        cells = []
        for k, t in enumerate(times):
            u = [at_time(c, t) for c in by["unguided"]]
            g = [at_time(c, t) for c in by["kdtree"]]
            cells += [f"{np.mean(u):.4f} ± {np.ptp(u) / 2:.4f}", f"{np.mean(g):.4f} ± {np.ptp(g) / 2:.4f}",
                      f"{r[scale][k]:.2f}"]
        lines.append(f"| {scale} | " + " | ".join(cells) + " |")
    its = {scale: {g: [c[-1][0] for c in by[g]] for g in GUIDES} for scale, by in cross.items()}
    lines += ["", "Iterations done (per seed): " + "; ".join(
        f"{scale}: unguided {'+'.join(map(str, its[scale]['unguided']))}, Kd-tree {'+'.join(map(str, its[scale]['kdtree']))}"
        for scale in cross) + ".", "", f"![ratio against scale]({args.name or f'guided_loop_{args.scene}'}.png)", ""]
    return "\n".join(lines)


def plot(path: Path, args, scores: dict, cross: dict):
    """Left: sweep score against learning rate per λ and estimator. Right: the equal-time ratio
    Kd-tree / unguided against the scale, at the three times."""
    plt = pyplot()
    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 3.8))
    for g, style in (("unguided", "o-"), ("kdtree", "s--")):
        for lam in args.lam:
            a.plot(args.lr, [scores[g][(lr, lam)] for lr in args.lr], style, label=f"{g}, λ {lam:g}")
    a.set_xscale("log", base=2)
    a.set_xlabel("learning rate")
    a.set_ylabel("Chamfer-L1, last sixth of the iterations")
    a.legend(fontsize=7)
    times = [args.seconds / 3, 2 * args.seconds / 3, args.seconds]
    r = ratios(cross, times)
    x = np.arange(len(r))
    for k, t in enumerate(times):
        b.plot(x, [r[s][k] for s in r], "o-", label=f"at {t:.0f} s")
    b.axhline(1.0, color="grey", lw=0.8)
    b.axhline(0.7, color="grey", lw=0.8, ls=":")
    b.set_xticks(x, list(r), fontsize=8)
    b.set_ylabel("Kd-tree / unguided Chamfer-L1 (equal time)")
    b.legend(fontsize=8)
    fig.tight_layout()
    save(fig, path)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", choices=list(BASES), default="shadow")
    ap.add_argument("--runs", type=Path, default=REPO / "runs" / "benchmarks" / "guided_loop")
    ap.add_argument("--out", type=Path, default=REPO / "docs" / "benchmarks")
    ap.add_argument("--lr", type=float, nargs="+", default=[0.025, 0.05, 0.1, 0.2], help="learning rates of the sweep")
    ap.add_argument("--lam", type=float, nargs="+", default=[5, 15, 50], help="LargeSteps λ of the sweep")
    ap.add_argument("--sweep-iterations", type=int, default=300, help="iterations per sweep run (no time budget)")
    ap.add_argument("--seconds", type=float, default=90.0, help="seconds per crossover run")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--scales", nargs="+", choices=list(SCALES), default=list(SCALES)[:4],
                    help="the crossover's scales (vertices ×16 needs several minutes per run)")
    ap.add_argument("--name", help="name of the outputs (default guided_loop_<scene>)")
    args = ap.parse_args(argv)
    args.runs.mkdir(parents=True, exist_ok=True)
    t0 = time.time()
    scores = sweep(args, args.runs)
    best = {g: min(s, key=s.get) for g, s in scores.items()}
    cross = crossover(args, args.runs, best)
    name = args.name or f"guided_loop_{args.scene}"
    with atomic_path(args.out / f"{name}.md") as tmp:
        tmp.write_text(report(args, scores, best, cross, time.time() - t0))
    with atomic_path(args.out / f"{name}.json") as tmp:
        tmp.write_text(json.dumps({"sweep": {g: {f"{lr:g},{lam:g}": v for (lr, lam), v in s.items()}
                                             for g, s in scores.items()},
                                   "best": {g: list(b) for g, b in best.items()},
                                   "crossover": cross}, indent=1))
    plot(args.out / f"{name}.png", args, scores, cross)
    print((args.out / f"{name}.md").read_text())


if __name__ == "__main__":
    main()
