#!/usr/bin/env python
"""Where an optimisation iteration's time goes: per phase (edge list, each term, the adjoint
render, loss, backward pass, update, state saving) and for the whole iteration, the wall time,
Dr.Jit's kernel execution, code generation and backend (compile / cache) time, the rest
("Python": tracing, numpy, launches, waits) and the kernels launched (JIT kernels, memsets, other
Dr.Jit operations), from Dr.Jit's kernel history (``dr.JitFlag.KernelHistory``).

The experiment is ``configs/reconstruct_bunny.yaml`` as ``psdr optimize`` runs it (one Dr.Jit
thread, batch 4, 1/4/1 spp with a 4-spp adjoint render), on its initial shape (the sphere
remeshed to 800 vertices), at the demo's 64² film and at 4× its pixels (128²); targets at 16 spp
(their content does not change the work). Each scale runs ``--warmup`` iterations (kernels
compiled or loaded from the cache) and then ``--iterations`` measured ones, the loop body of
:func:`psdr_cli.commands.optimize._optimize` (iterate, log row, apply, save the state) without
checkpoints. A phase is the time between entering and leaving one of the loop's functions; a
kernel belongs to the phase that launched it (Dr.Jit evaluates lazily: work traced in a term may
run in a later phase's kernel). ``reference`` is the time of a fixed Python loop of 10⁷ steps in
the same process: compare runs through their ratio to it.

    .venv/bin/python benchmarks/iteration_time.py [--scales 1,2] [--iterations 10] [--out docs/benchmarks]

``--max-depth`` and ``--terms`` change the experiment's path depth and terms (at depth ≥ 3 the
indirect term runs when listed); ``--compare-part NAME`` runs the recorded iteration twice per
scale, first with term NAME's recorded part left out (its passes traced, as before it had one),
then with it: the two side by side in one process, between the same reference loops; ``--rounds``
repeats the modes in turn (on a shared machine the load drifts: the rounds show by how much).
"""
from __future__ import annotations

import argparse
import json
import platform
import sys
import tempfile
import time
from collections import defaultdict
from dataclasses import replace
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import drjit as dr  # noqa: E402
from machine import reference_loop_seconds as reference_loop  # noqa: E402

import psdr_cli  # noqa: E402
from psdr_cli.commands.optimize import log_row, save_state  # noqa: E402
from psdr_cli.estimators import registry  # noqa: E402
from psdr_cli.losses import registry as loss_registry  # noqa: E402
from psdr_cli.optimisation import iteration  # noqa: E402
from psdr_cli.optimisation.engines import Engine  # noqa: E402
from psdr_cli.optimisation.frozen_batch import FrozenBatch  # noqa: E402
from psdr_cli.optimisation.iteration import GuideCache  # noqa: E402
from psdr_cli.optimisation.problem import Problem, SceneSource  # noqa: E402
from psdr_cli.optimisation.stages import stage_of  # noqa: E402
from psdr_cli.optimisation.start_state import initial_state, load_targets, read_targets  # noqa: E402
from psdr_cli.rendering.estimate import Settings  # noqa: E402
from psdr_cli.run_folder.layout import RunFiles  # noqa: E402
from psdr_cli.run_folder.log import append_log  # noqa: E402
from psdr_cli.support import backend  # noqa: E402

CONFIG = REPO / "configs" / "reconstruct_bunny.yaml"
FIELDS = ("wall", "execution", "codegen", "backend", "python", "kernels", "jit", "memset", "compiled")


class Phases:
    """Wall time and kernel history per phase; phases nest (a stack), time goes to the innermost."""

    def __init__(self):
        self.stack = ["other"]
        self.acc = defaultdict(lambda: dict.fromkeys(FIELDS, 0.0))
        self.t = time.perf_counter()

    def _flush(self):
        now = time.perf_counter()
        a = self.acc[self.stack[-1]]
        a["wall"] += now - self.t
        for k in dr.kernel_history():
            a["kernels"] += 1
            a["execution"] += k.get("execution_time", 0.0) / 1e3
            a["codegen"] += k.get("codegen_time", 0.0) / 1e3
            a["backend"] += k.get("backend_time", 0.0) / 1e3
            a["jit"] += k["type"] == dr.KernelType.JIT
            a["memset"] += k["type"] == dr.KernelType.Memset
            a["compiled"] += k["type"] == dr.KernelType.JIT and not k.get("cache_hit") and not k.get("cache_disk")
        self.t = time.perf_counter()  # the history's own cost is left out

    def enter(self, name):
        self._flush()
        self.stack.append(name)

    def leave(self):
        self._flush()
        self.stack.pop()

    def wrap(self, name, fn):
        def wrapped(*args, **kwargs):
            self.enter(name)
            try:
                return fn(*args, **kwargs)
            finally:
                self.leave()
        return wrapped

    def reset(self):
        self._flush()
        self.acc.clear()

    def result(self, n: int) -> dict:
        self._flush()
        out = {}
        for name, a in self.acc.items():
            a = {k: v / n for k, v in a.items()}
            a["python"] = a["wall"] - a["execution"] - a["codegen"] - a["backend"]
            out[name] = a
        total = dict.fromkeys(FIELDS, 0.0)
        for a in out.values():
            for k in FIELDS:
                total[k] += a[k]
        out["iteration"] = total
        return out


class DrProxy:
    """``drjit`` as :mod:`psdr_cli.optimisation.iteration` sees it, with ``dr.backward`` timed as a phase."""

    def __init__(self, phases):
        self._backward = phases.wrap("backward", dr.backward)

    def __getattr__(self, name):
        return self._backward if name == "backward" else getattr(dr, name)


def instrument(phases: Phases):
    """Time the loop's functions as phases (module attributes and registry entries patched)."""
    for name, term in list(registry._BY_NAME.items()):
        registry._BY_NAME[name] = term = replace(term, estimate=phases.wrap(name, term.estimate))
        if getattr(term, "estimate_views", None):  # a term that traces a batch's views as one wavefront
            registry._BY_NAME[name] = replace(term, estimate_views=phases.wrap(name, term.estimate_views))
    if hasattr(iteration, "GeometryAhead"):  # the edge table on a worker thread: its start and its wait
        iteration.GeometryAhead = timed_geometry(phases, iteration.GeometryAhead)
    else:
        iteration.edge_list = phases.wrap("edges", iteration.edge_list)
    if hasattr(iteration, "adjoint_images"):  # the views of a batch in one wavefront (after issue 38's batching)
        iteration.adjoint_images = phases.wrap("adjoint", iteration.adjoint_images)
    else:
        iteration.adjoint_image = phases.wrap("adjoint", iteration.adjoint_image)
    loss_registry.LOSSES = tuple(replace(x, value=phases.wrap("loss", x.value)) for x in loss_registry.LOSSES)
    iteration.dr = DrProxy(phases)
    FrozenBatch.__call__ = phases.wrap("frozen", FrozenBatch.__call__)
    for name, part in registry.RECORDED_PARTS.items():  # each boundary term's recorded part
        part.run = phases.wrap(f"frozen {name}", part.run)


def timed_geometry(phases: Phases, cls):
    """``GeometryAhead`` with its main-thread parts (reading the meshes, starting the worker;
    waiting for it and uploading the table) timed as the phase ``edges``: the worker's own numpy
    time overlaps other phases and shows only in the process's CPU time."""
    class Timed(cls):
        def __init__(self, *args):
            phases.wrap("edges", super().__init__)(*args)

        def edges(self):
            return phases.wrap("edges", super().edges)()
    return Timed


def setup(scale: int, tmp: Path, initial: int | None = None, depth: int | None = None, terms: tuple | None = None):
    """The demo's experiment at 64·scale pixels square, its initial shape remeshed to ``initial``
    vertices (None: the experiment's ``remesh.initial``), paths of ``depth`` segments and the
    estimator terms ``terms`` (None: the experiment's)."""
    exp = psdr_cli.load_experiment(CONFIG)
    remesh = exp.optimize.remesh if initial is None else replace(exp.optimize.remesh, initial=initial)
    scene = replace(exp.scene, width=64 * scale, height=64 * scale)
    scene = scene if depth is None else replace(scene, max_depth=depth)
    estimator = exp.estimator if terms is None else replace(exp.estimator, terms=terms)
    exp = replace(exp, output=tmp, scene=scene, estimator=estimator,
                  optimize=replace(exp.optimize, target_spp=16, remesh=remesh))
    backend.activate(exp)
    files = RunFiles(exp.run_dir)
    inputs = read_targets(exp, fresh=True)
    targets, cameras, _ = load_targets(exp, files, inputs)
    state = initial_state(exp, files, inputs.initial, print, inputs.initial_values)
    problem = Problem.from_state(SceneSource.of(exp), state, cameras)
    settings = Settings.from_experiment(exp, loop=True)
    engine = Engine(settings)
    stage = stage_of(problem, targets, engine.settings, engine.terms)
    return exp, files, problem, settings, engine, stage


def run_scale(scale: int, warmup: int, iterations: int, phases: Phases, initial: int | None = None,
              freeze: bool = False, *, depth: int | None = None, terms: tuple | None = None,
              traced_parts: tuple = ()) -> dict:
    """The breakdown at 64·scale pixels (module docstring); ``freeze``: with the recorded parts,
    but for those of ``traced_parts`` (their terms' passes traced)."""
    with tempfile.TemporaryDirectory() as tmp:
        exp, files, problem, settings, engine, stage = setup(scale, Path(tmp), initial, depth, terms)
        guides = GuideCache()
        problem.apply = phases.wrap("apply", problem.apply)
        problem.apply_leaves = phases.wrap("apply", problem.apply_leaves)
        problem.backward_leaves = phases.wrap("backward", problem.backward_leaves)
        problem.opt.step = phases.wrap("update", problem.opt.step)
        total = warmup + iterations
        seconds = 0.0
        loop = iteration.Loop(exp.optimize, engine, total, print, frozen=FrozenBatch() if freeze else None)
        for name in traced_parts if freeze else ():
            del loop.frozen.parts[name]  # the term's passes traced in the recorded iteration
        body = phases.wrap("step", lambda it: iteration.iterate(problem, loop, stage, guides, it))
        save = phases.wrap("save", lambda it, s: save_state(problem, files, it + 1, s, guides))
        with backend.optimization_threads():
            for it in range(total):
                if it == warmup:
                    phases.reset()
                    t0, c0 = time.perf_counter(), time.process_time()
                    recorded = loop.frozen.n_recordings if freeze else 0
                t_start = time.perf_counter()
                step = body(it)
                seconds += step.t_end - t_start
                append_log(files.log, log_row(it, step, t_start, seconds, problem, guides))
                problem.apply()
                save(it, seconds)
            wall = (time.perf_counter() - t0) / iterations
            cpu = (time.process_time() - c0) / iterations
        problem.release()
        out = phases.result(iterations)
        out["iteration"]["wall"] = wall  # the loop's own clock (the phases' sum without the history's cost)
        out["iteration"]["python"] = wall - sum(out["iteration"][k] for k in ("execution", "codegen", "backend"))
        out["iteration"]["cpu"] = cpu  # every thread's CPU time (the geometry worker's included)
        out["vertices"] = int(len(problem.vertices()))
        out["recordings"] = loop.frozen.n_recordings if freeze else 0
        out["recordings_measured"] = out["recordings"] - recorded  # recorded again in the measured iterations
        return out


ORDER = ("edges", "frozen", "frozen direct", "frozen primary", "frozen indirect", "interior", "primary", "direct",
         "indirect", "adjoint", "loss", "backward", "update", "step", "apply", "save", "other", "iteration")


def table(res: dict) -> list:
    rows = ["| phase | wall ms | kernel exec ms | codegen ms | backend ms | Python/other ms | kernels | JIT | memsets |",
            "|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for name in ORDER:
        if name not in res:
            continue
        a = res[name]
        label = "**iteration**" if name == "iteration" else name
        rows.append(f"| {label} | {a['wall'] * 1e3:.1f} | {a['execution'] * 1e3:.1f} | {a['codegen'] * 1e3:.1f} | "
                    f"{a['backend'] * 1e3:.1f} | {a['python'] * 1e3:.1f} | {a['kernels']:.1f} | {a['jit']:.1f} | "
                    f"{a['memset']:.1f} |")
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scales", default="1,2", help="film scales: 1 = 64², 2 = 128²")
    ap.add_argument("--warmup", type=int, default=3)
    ap.add_argument("--iterations", type=int, default=10)
    ap.add_argument("--json", type=Path, default=None, help="write the results here")
    ap.add_argument("--label", default="")
    ap.add_argument("--initial", type=int, default=None,
                    help="vertices of the initial shape (default: the experiment's remesh.initial, 800; the demo "
                         "remeshes to 1500 and 2500 later)")
    ap.add_argument("--freeze", choices=("off", "on", "both"), default="both",
                    help="the recorded part of the iteration (psdr_cli/optimisation/frozen_batch.py): off, on, or both in turn")
    ap.add_argument("--max-depth", type=int, default=None, help="the scene's path depth (default: the experiment's, 2)")
    ap.add_argument("--terms", default=None,
                    help="estimator terms, comma-separated (default: the experiment's: interior,primary,direct)")
    ap.add_argument("--compare-part", default=None,
                    help="a term with a recorded part: the recorded iteration with that part traced, then recorded "
                         "(overrides --freeze)")
    ap.add_argument("--rounds", type=int, default=1, help="run the modes this many times in turn")
    ap.add_argument("--no-blocking", action="store_true",
                    help="asynchronous launches (the loop's mode): kernel times then overlap and include queueing")
    args = ap.parse_args(argv)
    phases = Phases()
    instrument(phases)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    dr.set_flag(dr.JitFlag.LaunchBlocking, not args.no_blocking)
    results = {"label": args.label, "python": platform.python_version(), "drjit": dr.__version__,
               "reference_before": reference_loop(), "scales": {}}
    modes = [(freeze, ()) for freeze in {"off": (False,), "on": (True,), "both": (False, True)}[args.freeze]]
    if args.compare_part:
        modes = [(True, (args.compare_part,)), (True, ())]
    terms = tuple(args.terms.split(",")) if args.terms else None
    results.update(max_depth=args.max_depth, terms=terms, compare_part=args.compare_part)
    for s in (int(x) for x in args.scales.split(",")):
        for (freeze, traced), round_ in [(m, r) for r in range(args.rounds) for m in modes]:
            res = run_scale(s, args.warmup, args.iterations, phases, args.initial, freeze, depth=args.max_depth,
                            terms=terms, traced_parts=traced)
            key = f"{64 * s}x{64 * s}" + (" frozen" if freeze else "") + "".join(f", {t} traced" for t in traced) \
                + (f" (round {round_ + 1})" if args.rounds > 1 else "")
            results["scales"][key] = res
            print(f"\n{args.label} {key} ({res['vertices']} vertices, {res['recordings']} recordings, "
                  f"{res['recordings_measured']} of them measured), per iteration "
                  f"over {args.iterations}:")
            print("\n".join(table(res)))
            print(f"CPU time of the process (every thread): {res['iteration']['cpu'] * 1e3:.1f} ms per iteration")
    results["reference_after"] = reference_loop()
    print(f"reference loop (10⁷ steps): {results['reference_before']:.3f} s before, "
          f"{results['reference_after']:.3f} s after")
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
