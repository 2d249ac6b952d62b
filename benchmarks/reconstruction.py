#!/usr/bin/env python
"""Equal-time shape reconstruction: psdr's estimators, guided and not, vs Mitsuba's own recipe, in one loop.

For every scene (the bunny of ``configs/reconstruct_bunny.yaml`` and the stand-ins
``reconstruct_ears.yaml`` (thin ears) and ``reconstruct_groove.yaml`` (creases, concave groove);
with ``--scenes shadow glass`` the two Fig. 10 experiments) and every seed, one run of ``psdr
optimize`` per engine (``--engines``, default psdr and mitsuba) fits the same targets from the same
initial sphere with the same batches, L1 loss, LargeSteps, Adam and remeshing; they differ only
in the estimator (and, with ``--lr ENGINE=RATE``, in the learning rate):

- **psdr**: the experiment's own estimator (interior + primary + direct terms);
- **psdr-kdtree**: the same, the direct term guided by Kd-trees fitted to the loop's own samples
  (:mod:`psdr_cli.guiding.loop_fed`; MIS, sorted edges);
- **mitsuba**: Mitsuba's ``direct_projective`` (``prb_projective`` for deeper paths) as its
  shape-optimisation tutorial sets it up (shadow term off, 16 spp; :mod:`psdr_cli.optimisation.engines`), the
  loss's sign taken from that same render as in the tutorial (``optimize.adjoint_spp`` 0,
  whatever the experiment sets);
- **mitsuba-shadows**: the same with its shadow (indirect-visibility) term on, the only Mitsuba
  recipe that sees shapes carried by shadows or glass (the Fig. 10 scenes).

**Load sharing.** All runs live in one process and advance in rounds: in round k every run is
resumed until its optimisation time reaches k·``--chunk`` seconds (``optimize.seconds`` and
``--resume``; a resumed run is bit-identical to an uninterrupted one), the engine that goes first
alternating between rounds. Whatever else the machine runs then slows both engines alike. The
1-minute load average is sampled after every chunk and reported.

**Shape error** of every checkpoint (every ``checkpoint_every`` iterations, and the final mesh)
against the ground truth, both normalised with the ground truth's bounding box (longest side 1):
Chamfer-L1 = ½(mean_P d(p, Q) + mean_Q d(q, P)) and Hausdorff = max(max_P d, max_Q d)
(:func:`psdr_cli.commands.evaluate.distance`), plotted against the run's optimisation seconds.

Outputs: ``<out>/reconstruction.md`` (table), ``reconstruction.png`` (Chamfer-L1 and Hausdorff
against seconds, one panel per scene), ``reconstruction.json``.

    .venv/bin/python benchmarks/reconstruction.py                  # 3 scenes × 2 seeds × 120 s each
    .venv/bin/python benchmarks/reconstruction.py --quick          # 32², 90 s, one scene (bunny)
    .venv/bin/python benchmarks/reconstruction.py --quick --scenes bunny ears groove
    .venv/bin/python benchmarks/reconstruction.py --psdr-spp 1 4 1 4 --mitsuba-spp 4 --name reconstruction_low_spp

``--psdr-spp`` replaces the experiment's interior, primary and boundary spp and adjoint spp,
``--mitsuba-spp`` the recipe's 16; ``--name`` names the outputs and the runs' folder.

**The loop's own floor** (``--from-truth N``): every run starts from the ground truth itself,
remeshed to N vertices with the experiment's remesher, and is not remeshed again. Where the
errors settle is the stationary error of this loop (L1 on 64² targets, Adam's constant step,
LargeSteps) with each engine's gradients: the lowest error either engine's run can be expected to
hold, so it bounds the psdr / Mitsuba ratio that any gradient can reach at equal time. The
report adds each scene's metric floor: the distance of the ground truth to itself with
independent surface samples (:func:`psdr_cli.commands.evaluate.noise_floor`).

    .venv/bin/python benchmarks/reconstruction.py --from-truth 2500 --seconds 60 --chunk 30 \
        --psdr-spp 1 4 1 4 --mitsuba-spp 4 --name reconstruction_floor
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import psdr_cli  # noqa: E402,F401  (configures Dr.Jit / LLVM before drjit is imported)
from psdr_cli.commands import evaluate as ev  # noqa: E402
from psdr_cli.commands.optimize import optimize  # noqa: E402
from psdr_cli.config.optimize_section import RemeshConfig  # noqa: E402
from psdr_cli.config.options import with_estimator  # noqa: E402
from psdr_cli.experiment.load import load_experiment  # noqa: E402
from psdr_cli.run_folder.layout import RunFiles  # noqa: E402
from psdr_cli.run_folder.log import read_log  # noqa: E402
from psdr_cli.support.fileio import atomic_path  # noqa: E402
from psdr_cli.support.plots import pyplot, save  # noqa: E402

SCENES = {"bunny": "configs/reconstruct_bunny.yaml", "ears": "configs/reconstruct_ears.yaml",
          "groove": "configs/reconstruct_groove.yaml", "shadow": "configs/paper/cpu/fig10_shadow.yaml",
          "glass": "configs/paper/cpu/fig10_glass.yaml"}
#: what each engine of ``--engines`` runs: the experiment's own estimator, the same with loop-fed
#: Kd-tree guides of the direct term (MIS, sorted edges), Mitsuba's recipe (shadow term off), and
#: Mitsuba with its shadow (indirect-visibility) term on
ENGINES = ("psdr", "psdr-kdtree", "mitsuba", "mitsuba-shadows")
COLOURS = {"psdr": "tab:blue", "psdr-kdtree": "tab:green", "mitsuba": "tab:orange", "mitsuba-shadows": "tab:red"}


def quick_experiment(exp):
    """The experiment at CPU-smoke scale: 32² film, 500 → 1000 vertices (remesh at 40)."""
    scene = replace(exp.scene, width=32, height=32)
    opt = replace(exp.optimize, remesh=RemeshConfig(exp.optimize.remesh.method, 500, (40,), (1000,)),
                  target_spp=64, checkpoint_every=10)
    return replace(exp, scene=scene, optimize=opt)


def from_truth_experiment(exp, vertices: int):
    """The experiment started from its ground truth (the optimised object's mesh, or
    ``optimize.target.mesh``, with the object's transform) remeshed to ``vertices``, never
    remeshed again."""
    obj = next(o for o in exp.scene.objects if o.name == exp.optimize.object)
    remesh = RemeshConfig(exp.optimize.remesh.method, vertices, (), ())
    return replace(exp, optimize=replace(exp.optimize, init=exp.optimize.target_mesh or obj.mesh,
                                         init_transform=obj.transform, remesh=remesh))


def run_experiment(base, engine: str, seed: int, root: Path, psdr_spp=None, mitsuba_spp: int = 16,
                   learning_rate: float | None = None):
    """One run of ``engine`` (:data:`ENGINES`): ``base`` with its estimator and ``seed`` replaced,
    the targets of the base seed, a folder ``<root>/<engine>_s<seed>``, no iteration limit (the
    time decides). ``psdr_spp``: (interior, primary, boundary, adjoint) spp replacing the
    experiment's; ``learning_rate`` replaces the experiment's."""
    psdr = engine.startswith("psdr")
    if psdr and psdr_spp:
        base = with_estimator(base, spp=psdr_spp[0], primary_spp=psdr_spp[1], boundary_spp=psdr_spp[2])
        base = replace(base, optimize=replace(base.optimize, adjoint_spp=psdr_spp[3]))
    if engine == "psdr":
        exp = with_estimator(base, engine="psdr")
    elif engine == "psdr-kdtree":
        exp = with_estimator(base, engine="psdr", guiding="kdtree", edge_sort=True)
    else:
        exp = with_estimator(base, engine="mitsuba", mitsuba_spp=mitsuba_spp,
                             mitsuba_shadows=engine == "mitsuba-shadows")
    opt = replace(exp.optimize, target_seed=base.seed, iterations=100_000, preview_views=(0,),
                  adjoint_spp=exp.optimize.adjoint_spp if psdr else 0,
                  learning_rate=learning_rate or exp.optimize.learning_rate, variants=())
    return replace(exp, seed=seed, name=f"{engine}_s{seed}", output=root, optimize=opt)


def advance(exp, seconds: float, first: bool):
    """Continue ``exp`` until its optimisation time reaches ``seconds``."""
    run = replace(exp, optimize=replace(exp.optimize, seconds=seconds))
    return optimize(run, resume=not first, warn=lambda m: None)


def record_load(folder: Path, load: float):
    """Append a load sample to ``<folder>/loads.json`` (a scene's runs' folder)."""
    with atomic_path(folder / "loads.json") as tmp:
        Path(tmp).write_text(json.dumps(recorded_loads(folder) + [load]))


def recorded_loads(folder: Path) -> list:
    path = folder / "loads.json"
    return json.loads(path.read_text()) if path.exists() else []


def errors(exp, samples: int) -> list:
    """[(iteration, seconds, Chamfer-L1, Hausdorff)] of every checkpoint of a run."""
    files = RunFiles(exp.run_dir)
    reference = ev.load(files.reference)
    rows = read_log(files.log)
    seconds = {int(r["iteration"]) + 1: float(r["seconds_total"]) for r in rows}
    seconds[0] = 0.0
    out = []
    for path in sorted(files.checkpoints.glob("iter_*.ply")):
        it = int(path.stem.split("_")[1])
        if it in seconds:
            d = ev.distance(ev.load(path), reference, samples)
            out.append((it, seconds[it], d.chamfer_l1, d.hausdorff))
    return out


def at_time(curve: list, t: float):
    """(Chamfer-L1, Hausdorff, iteration) when the run's time reached ``t`` seconds: the checkpoint written
    by the iteration that crossed it (a round's time budget ends a run there)."""
    done = [c for c in curve if c[1] >= t - 1e-9] or curve[-1:]
    return done[0][2], done[0][3], done[0][0]


def table(results: dict, times: list, engines) -> str:
    """Markdown: per scene and time, mean ± half-range over seeds of Chamfer-L1 and Hausdorff for
    every engine, the ratio of each engine's mean to the first engine's, and each seed's
    iterations done by then."""
    head = ["iterations " + " / ".join(engines)]
    for metric in ("Chamfer-L1", "Hausdorff"):
        head += [f"{e} {metric}" for e in engines] + [f"{e} / {engines[0]}" for e in engines[1:]]
    lines = ["| scene | seconds | " + " | ".join(head) + " |", "|---|---|" + "---|" * len(head)]
    for scene, runs in results.items():
        for t in times:
            its = {e: "+".join(str(at_time(c, t)[2]) for (e2, _), c in runs.items() if e2 == e) for e in engines}
            cells = [" / ".join(its[e] for e in engines)]
            for metric in (0, 1):
                means = {}
                for engine in engines:
                    v = np.array([at_time(c, t)[metric] for (e, _), c in runs.items() if e == engine])
                    means[engine] = float(np.mean(v))
                    cells.append(f"{np.mean(v):.4f} ± {(v.max() - v.min()) / 2:.4f}")
                cells += [f"{means[e] / means[engines[0]]:.2f}" for e in engines[1:]]
            lines.append(f"| {scene} | {t:g} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def plot(path: Path, results: dict):
    """Chamfer-L1 (top) and Hausdorff (bottom) against optimisation seconds, a column per scene."""
    plt = pyplot()
    fig, axes = plt.subplots(2, len(results), figsize=(4.2 * len(results), 6.5), squeeze=False)
    for col, (scene, runs) in enumerate(results.items()):
        for (engine, seed), curve in runs.items():
            t = [c[1] for c in curve]
            for row, metric in ((0, 2), (1, 3)):
                axes[row][col].plot(t, [c[metric] for c in curve], "o-", ms=2, color=COLOURS[engine],
                                    alpha=0.9 if seed == 0 else 0.55,
                                    label=f"{engine} (seed {seed})")
        axes[0][col].set_title(scene)
        for row, name in ((0, "Chamfer-L1"), (1, "Hausdorff")):
            axes[row][col].set_yscale("log")
            axes[row][col].set_xlabel("optimisation seconds")
            axes[row][col].set_ylabel(f"{name} (reference bbox = 1)")
        axes[0][col].legend(fontsize=7)
    fig.tight_layout()
    save(fig, path)


def allocations(args) -> str:
    """What each engine runs, as the report states it."""
    psdr = ("the experiment's estimator and adjoint render" if not args.psdr_spp else
            "interior/primary/boundary spp {}/{}/{}, a {}-spp adjoint render".format(*args.psdr_spp))
    said = {"psdr": f"`psdr`: {psdr}",
            "psdr-kdtree": "`psdr-kdtree`: the same with the direct term guided by Kd-trees fitted to the loop's "
                           "own samples (MIS, sorted edges)",
            "mitsuba": f"`mitsuba`: Mitsuba's projective integrator, shadow term off, {args.mitsuba_spp} spp, the "
                       "loss on that render (the tutorial's recipe" + (")" if args.mitsuba_spp == 16 else
                                                                   f", at {args.mitsuba_spp} instead of 16 spp)"),
            "mitsuba-shadows": f"`mitsuba-shadows`: Mitsuba's projective integrator with its shadow (indirect-visibility) "
                               f"term on, {args.mitsuba_spp} spp, the loss on that render"}
    rates = "; learning rates " + ", ".join(f"{e} {r:g}" for e, r in args.lr.items()) if args.lr else ""
    return "; ".join(said[e] for e in args.engines) + rates + ". "


def write_report(out: Path, args, results: dict, loads: list, wall: float, times: list, floors: dict):
    """``<name>.md``, ``.json`` and ``.png``; ``floors``: {scene: (Chamfer-L1, Hausdorff)} of
    the metric's own floor (reported with ``--from-truth``; empty otherwise)."""
    md = [f"# Shape reconstruction at equal time: {', '.join(args.engines)}",
          "",
          f"`benchmarks/reconstruction.py {' '.join(sys.argv[1:])}` — {time.strftime('%Y-%m-%d %H:%M')}, "
          f"{platform.machine()}, {os.cpu_count()} cores, Dr.Jit threads per optimisation: "
          f"{os.environ.get('PSDR_OPTIMIZE_THREADS', '1')}.",
          f"Machine load while it ran (1-minute load average after each chunk, this benchmark included): "
          f"mean {np.mean(loads):.2f}, min {np.min(loads):.2f}, max {np.max(loads):.2f}; wall time {wall / 60:.1f} min.",
          "",
          ("Same loop, targets, initial sphere, batches, L1 loss, LargeSteps λ, Adam, remeshing; " if not args.from_truth
           else f"Same loop, targets, batches, L1 loss, LargeSteps λ, Adam; every run starts from the ground truth "
                f"remeshed to {args.from_truth} vertices and is not remeshed again (the loop's floor). ")
          + allocations(args) + "Runs advance in alternating chunks of "
          f"{args.chunk:g} s so that load is shared. Errors are normalised by the ground truth's bounding box; "
          f"mean ± half-range over seeds; ratios to {args.engines[0]} (< 1: better than it).",
          "",
          table(results, times, args.engines),
          "",
          *([] if not floors else ["Metric floor (the ground truth against itself, independent samples, "
                                   f"{args.samples} points per mesh): "
                                   + ", ".join(f"{sc} Chamfer-L1 {c:.4f}, Hausdorff {h:.4f}" for sc, (c, h) in floors.items())
                                   + ".", ""]),
          f"![Chamfer-L1 and Hausdorff against optimisation seconds]({args.name}.png)",
          ""]
    with atomic_path(out / f"{args.name}.md") as tmp:
        Path(tmp).write_text("\n".join(md))
    data = {scene: {f"{e}_s{s}": c for (e, s), c in runs.items()} for scene, runs in results.items()}
    with atomic_path(out / f"{args.name}.json") as tmp:
        Path(tmp).write_text(json.dumps({"args": vars(args) | {"out": str(args.out), "runs": str(args.runs)},
                                         "loads": loads, "curves": data, "metric_floor": floors}, indent=1))
    plot(out / f"{args.name}.png", results)


def learning_rates(ap, args) -> dict:
    """{engine: learning rate} from ``--lr ENGINE=RATE`` (an error for an engine not compared)."""
    rates = {}
    for item in args.lr:
        engine, _, rate = item.partition("=")
        if engine not in args.engines:
            ap.error(f"--lr {item}: '{engine}' is not among --engines")
        try:
            rates[engine] = float(rate)
        except ValueError:
            ap.error(f"--lr {item}: expected ENGINE=RATE with a number")
    return rates


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="32² film, 90 s per run, bunny only (unless --scenes)")
    ap.add_argument("--scenes", nargs="+", choices=list(SCENES),
                    help="scenes (default: bunny, ears, groove; quick: bunny)")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1], help="seeds per engine")
    ap.add_argument("--engines", nargs="+", choices=ENGINES, default=["psdr", "mitsuba"],
                    help="what to compare (the first is the ratios' denominator)")
    ap.add_argument("--lr", nargs="+", default=[], metavar="ENGINE=RATE",
                    help="an engine's learning rate (default: the experiment's)")
    ap.add_argument("--seconds", type=float, help="optimisation seconds per run (default 120; quick: 90)")
    ap.add_argument("--chunk", type=float, help="seconds per run and round (default 40; quick: 30)")
    ap.add_argument("--samples", type=int, default=50_000, help="surface points per mesh for the distances")
    ap.add_argument("--evaluate-only", action="store_true",
                    help="no optimisation: evaluate the runs already in --runs (e.g. scenes run separately)")
    ap.add_argument("--runs", type=Path, default=REPO / "runs" / "benchmarks", help="run folders (under <runs>/<name>/)")
    ap.add_argument("--out", type=Path, default=REPO / "docs" / "benchmarks", help="output folder")
    ap.add_argument("--psdr-spp", type=int, nargs=4, metavar=("I", "P", "B", "A"),
                    help="psdr's interior, primary, boundary and adjoint spp (default: the experiment's)")
    ap.add_argument("--mitsuba-spp", type=int, default=16, help="spp of Mitsuba's recipe")
    ap.add_argument("--name", default="reconstruction", help="name of the outputs and of the runs' folder")
    ap.add_argument("--from-truth", type=int, metavar="N",
                    help="start from the ground truth remeshed to N vertices, no remeshing (the loop's floor)")
    args = ap.parse_args(argv)
    args.lr = learning_rates(ap, args)
    scenes = args.scenes or (["bunny"] if args.quick else ["bunny", "ears", "groove"])
    seconds = args.seconds or (90.0 if args.quick else 120.0)
    args.chunk = args.chunk or (30.0 if args.quick else 40.0)
    rounds = int(np.ceil(seconds / args.chunk))
    runs = {}
    for scene in scenes:
        base = load_experiment(REPO / SCENES[scene])
        base = quick_experiment(base) if args.quick else base
        base = from_truth_experiment(base, args.from_truth) if args.from_truth else base
        for seed in args.seeds:
            for engine in args.engines:
                folder = args.runs / args.name / ("quick" if args.quick else "full") / scene
                runs[(scene, engine, seed)] = run_experiment(base, engine, seed, folder, args.psdr_spp, args.mitsuba_spp,
                                                             args.lr.get(engine))
    loads, t0 = [], time.time()
    for folder in {exp.output for exp in runs.values()} if not args.evaluate_only else ():
        (folder / "loads.json").unlink(missing_ok=True)  # a fresh benchmark of this scene
    for k in range(1, 0 if args.evaluate_only else rounds + 1):
        budget = min(k * args.chunk, seconds)
        first = args.engines if k % 2 else args.engines[::-1]  # the engines take turns going first
        for key, exp in sorted(runs.items(), key=lambda kv: (kv[0][0], kv[0][2], first.index(kv[0][1]))):
            advance(exp, budget, first=k == 1)
            loads.append(os.getloadavg()[0])
            record_load(exp.output, loads[-1])
            print(f"round {k}/{rounds}: {key[0]} {key[1]} seed {key[2]} at {budget:g} s "
                  f"(load {loads[-1]:.2f}, {(time.time() - t0) / 60:.1f} min)", flush=True)
    if args.evaluate_only:
        loads = [x for exp in {e.output: e for e in runs.values()}.values() for x in recorded_loads(exp.output)]
    results = {}
    for (scene, engine, seed), exp in runs.items():
        results.setdefault(scene, {})[(engine, seed)] = errors(exp, args.samples)
    times = sorted({min(k * args.chunk, seconds) for k in (max(rounds // 3, 1), max(2 * rounds // 3, 1), rounds)})
    args.out.mkdir(parents=True, exist_ok=True)
    floors = {}
    for (scene, engine, seed), exp in runs.items():
        if args.from_truth and scene not in floors:
            d = ev.noise_floor(ev.load(RunFiles(exp.run_dir).reference), args.samples)
            floors[scene] = (d.chamfer_l1, d.hausdorff)
    write_report(args.out, args, results, loads, time.time() - t0, times, floors)
    print((args.out / f"{args.name}.md").read_text())


if __name__ == "__main__":
    main()
