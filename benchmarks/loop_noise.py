#!/usr/bin/env python
"""Is the optimisation loop limited by gradient noise? Shape error per iteration against the
boundary samples, the mesh resolution, the learning rate and the guide.

A guide can only pay in ``psdr optimize`` if a lower-variance gradient reaches a better shape in
the same number of iterations. This benchmark measures that directly, without any timing: each
configuration is the Fig. 10 shadow experiment (``configs/paper/cpu/fig10_shadow.yaml``, where
the direct boundary term carries all of the shape) run for a fixed number of iterations (its
``seconds`` budget and variants removed, a checkpoint every 50 iterations) with one change:

- ``boundary_spp`` 1, 2, 8 (the experiment's), 32 at learning rate 0.1: more samples lower the
  variance of the direct term (∝ 1/spp);
- the same at four times the vertices (remesh to 2400 → 4800 → 8000 instead of 600 → 1200 → 2000),
  and at a 96² film instead of 48², 8 and 32 spp;
- learning rates 0.05, 0.1, 0.2, 0.4 at 8 and 32 spp, unguided;
- learning rates 0.025, 0.05, 0.1 with the direct term guided by Kd-trees fitted to the loop's
  own samples (``guiding: kdtree``, MIS, sorted edges), 8 spp; and at its best rate (0.05) at
  2 spp, at four times the vertices and at the 96² film.

Each run is ``psdr optimize`` on a generated YAML file, then ``psdr evaluate`` (Chamfer-L1 of
every checkpoint against the ground truth, bounding box 1). One seed per configuration (the
experiment's); finished runs are reused. Outputs: ``<out>/loop_noise.md``, ``.json``, ``.png``.

    .venv/bin/python benchmarks/loop_noise.py --runs runs/benchmarks/loop_noise
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

import yaml

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from psdr_cli.support.fileio import atomic_path  # noqa: E402
from psdr_cli.support.plots import pyplot, save  # noqa: E402

BASE = REPO / "configs" / "paper" / "cpu" / "fig10_shadow.yaml"
#: name -> (learning rate, boundary spp, guiding, scale: vertices ×4 ("v4") or film ×2 ("f2") or None)
RUNS = {
    **{f"s_lr0.1_b{b}": (0.1, b, "none", None) for b in (1, 2, 8, 32)},
    **{f"v4_lr0.1_b{b}": (0.1, b, "none", "v4") for b in (8, 32)},
    **{f"f2_lr0.1_b{b}": (0.1, b, "none", "f2") for b in (8, 32)},
    **{f"s_lr{lr}_b{b}": (lr, b, "none", None) for lr in (0.05, 0.2, 0.4) for b in (8, 32)},
    **{f"kd_lr{lr}_b8": (lr, 8, "kdtree", None) for lr in (0.025, 0.05, 0.1)},
    "kd_lr0.05_b2": (0.05, 2, "kdtree", None),
    "kd_v4_lr0.05_b8": (0.05, 8, "kdtree", "v4"),
    "kd_f2_lr0.05_b8": (0.05, 8, "kdtree", "f2"),
}


def experiment(name: str, lr: float, spp: int, guiding: str, scale, runs: Path, iterations: int) -> dict:
    """The shadow experiment changed as the module docstring says."""
    d = copy.deepcopy(yaml.safe_load(BASE.read_text()))
    d["name"], d["output"] = name, str(runs)
    d["estimator"]["boundary_spp"], d["estimator"]["guiding"] = spp, guiding
    if guiding == "kdtree":
        d["estimator"]["edge_sort"] = True
    o = d["optimize"]
    o.pop("variants")
    o.pop("seconds")
    o.update(iterations=iterations, learning_rate=lr, checkpoint_every=50)
    if scale == "v4":
        o["remesh"].update(initial=2400, vertices=[4800, 8000])
    if scale == "f2":
        d["scene"]["film"] = {"width": 96, "height": 96}
    return d


def run(name: str, data: dict, runs: Path) -> list:
    """[(iteration, Chamfer-L1)] of a finished run (optimised and evaluated unless done before)."""
    cfg = runs / f"{name}.yaml"
    result = runs / name / "eval.json"
    if not result.exists():
        cfg.write_text(yaml.safe_dump(data, sort_keys=False))
        for cmd in (["optimize", str(cfg)], ["evaluate", str(cfg), "--json", str(result)]):
            subprocess.run([sys.executable, "-m", "psdr_cli", *cmd], check=True, cwd=REPO,
                           stdout=subprocess.DEVNULL)
    meshes = json.loads(result.read_text())["meshes"]
    return sorted((m["iteration"], m["chamfer_l1"]) for m in meshes)


def table(curves: dict) -> list:
    its = [it for it, _ in next(iter(curves.values()))][1:]
    out = ["| run | learning rate | boundary spp | guide | scale | " + " | ".join(f"it. {i}" for i in its) + " |",
           "|---|---|---|---|---|" + "---|" * len(its)]
    names = {None: "experiment's", "v4": "vertices ×4", "f2": "film 96²"}
    for name, curve in curves.items():
        lr, spp, guiding, scale = RUNS[name]
        out.append(f"| {name} | {lr:g} | {spp} | {guiding} | {names[scale]} | "
                   + " | ".join(f"{c:.4f}" for _, c in curve[1:]) + " |")
    return out


def plot(path: Path, curves: dict):
    """Mean Chamfer-L1 of the last three checkpoints (one run's last value jumps with its steps)
    against boundary spp (unguided at lr 0.1, the loop-fed Kd-tree at 0.05: each one's best; both
    mesh resolutions) and against the learning rate (unguided 8 and 32 spp, Kd-tree 8 spp)."""
    plt = pyplot()
    fig, (a, b) = plt.subplots(1, 2, figsize=(9, 3.6))
    last = {n: sum(c for _, c in curve[-3:]) / len(curve[-3:]) for n, curve in curves.items()}
    for scale, style, colour, said in ((None, "o-", "tab:blue", ""), ("v4", "s--", "tab:orange", ", vertices ×4"),
                                       ("f2", "^:", "tab:purple", ", film 96²")):
        pts = sorted((RUNS[n][1], last[n]) for n in curves if RUNS[n][0] == 0.1 and RUNS[n][2] == "none"
                     and RUNS[n][3] == scale)
        a.plot(*zip(*pts), style, color=colour, label="unguided, lr 0.1" + said)
        pts = sorted((RUNS[n][1], last[n]) for n in curves if RUNS[n][0] == 0.05 and RUNS[n][2] == "kdtree"
                     and RUNS[n][3] == scale)
        a.plot(*zip(*pts), style, color="tab:green", mfc=None if scale is None else "none",
               label="Kd-tree (loop-fed), lr 0.05" + said)
    a.set_xscale("log", base=2)
    a.set_xlabel("boundary spp (each at its best learning rate)")
    a.set_ylabel("Chamfer-L1, mean of the last 3 checkpoints")
    a.legend(fontsize=8)
    for label, pick in (("unguided, 8 spp", ("none", 8)), ("unguided, 32 spp", ("none", 32)),
                        ("Kd-tree (loop-fed), 8 spp", ("kdtree", 8))):
        pts = sorted((RUNS[n][0], last[n]) for n in curves if (RUNS[n][2], RUNS[n][1]) == pick and RUNS[n][3] is None)
        b.plot(*zip(*pts), "o-", label=label)
    b.set_xscale("log", base=2)
    b.set_xlabel("learning rate")
    b.legend(fontsize=8)
    fig.tight_layout()
    save(fig, path)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=Path, default=REPO / "runs" / "benchmarks" / "loop_noise")
    ap.add_argument("--out", type=Path, default=REPO / "docs" / "benchmarks")
    ap.add_argument("--iterations", type=int, default=300)
    args = ap.parse_args(argv)
    args.runs.mkdir(parents=True, exist_ok=True)
    t0 = time.time()
    curves = {}
    for name, (lr, spp, guiding, scale) in RUNS.items():
        curves[name] = run(name, experiment(name, lr, spp, guiding, scale, args.runs, args.iterations), args.runs)
        print(f"{name}: Chamfer-L1 {curves[name][-1][1]:.4f} at iteration {curves[name][-1][0]}", flush=True)
    md = ["# Is the loop limited by gradient noise? (fig10_shadow, shape error per iteration)", "",
          f"`benchmarks/loop_noise.py {' '.join(sys.argv[1:])}` — {time.strftime('%Y-%m-%d %H:%M')}, "
          f"{platform.machine()}, {os.cpu_count()} cores, {(time.time() - t0) / 60:.1f} min (finished runs reused). "
          "Chamfer-L1 (ground truth's bounding box = 1) of the checkpoints; one seed each.", "",
          *table(curves), "", "![Chamfer-L1 against boundary spp and learning rate](loop_noise.png)", ""]
    args.out.mkdir(parents=True, exist_ok=True)
    with atomic_path(args.out / "loop_noise.md") as tmp:
        Path(tmp).write_text("\n".join(md))
    with atomic_path(args.out / "loop_noise.json") as tmp:
        Path(tmp).write_text(json.dumps({"runs": {n: {"config": dict(zip(("learning_rate", "boundary_spp", "guiding",
                                                                            "scale"), RUNS[n])),
                                                      "chamfer_l1": c} for n, c in curves.items()}}, indent=1))
    plot(args.out / "loop_noise.png", curves)
    print("\n".join(md))


if __name__ == "__main__":
    main()
