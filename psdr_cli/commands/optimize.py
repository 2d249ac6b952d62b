"""Inverse rendering (``psdr optimize``): reconstruct an object's shape from images. Owns the
loop over iterations; reads the experiment and the targets; writes the run folder.

Each iteration renders a mini-batch of views with the psdr estimator in reverse mode (or with
Mitsuba's projective integrators: ``estimator.engine``, :mod:`psdr_cli.optimisation.engines`) and takes one
step on the L1 image loss

    L = (1/|B|) Σ_{v ∈ B} mean |I_v(x) − T_v|,

with the vertex positions x parametrised by the "large steps" latent u = (I + λL) x (Nicolet et
al. 2021, ``mi.ad.LargeSteps``) and updated by ``mi.ad.Adam(uniform=True)``. The object's albedo
and the environment's rotation angle can be optimised jointly. The shape is remeshed
(field-aligned, :mod:`psdr_cli.geometry.remesh`) before the first iteration and on a schedule.

Nothing already saved is lost: the state (mesh, optimiser moments, iteration) is written
atomically after every iteration, checkpoints and previews at ``checkpoint_every``, and
``resume=True`` continues from the saved state. View batches and sample seeds depend only on
(seed, iteration), so a resumed run draws what the uninterrupted run would have drawn.

An optional wall-clock budget (``optimize.seconds``, optimisation time only) ends a run early,
for equal-time comparisons; ``optimize.variants`` turns one experiment into an ablation whose
runs (estimator overrides) live in ``<output>/<name>/<label>/``
(:func:`psdr_cli.run_folder.variant_folders.variant_experiments`; the run-folder layout is :mod:`psdr_cli.run_folder`).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import drjit as dr

from ..config.experiment_file import Experiment, check_experiment
from ..errors import PsdrError
from ..losses.registry import PLOT_LABEL
from ..optimisation.camera_refinement import with_camera_mode
from ..optimisation.engines import Engine
from ..optimisation.frozen_batch import FrozenBatch
from ..optimisation.iteration import GuideCache, Loop, iterate
from ..optimisation.outlier_clip import clip_factor
from ..optimisation.photo_light import with_photograph_light
from ..optimisation.problem import Problem, SceneSource, remeshed_problem
from ..optimisation.stages import Stage, stage_of
from ..optimisation.start_state import dataset_coordinates, initial_state, load_targets, read_targets
from ..rendering.estimate import Settings, guiding_line
from ..rendering.render import render_view
from ..run_folder.checkpoints import write_checkpoint, write_mesh
from ..run_folder.layout import RunFiles, keep_previous_run, lock_run
from ..run_folder.log import append_log, plot_loss, read_log, write_log
from ..run_folder.record import run_record
from ..run_folder.state import resumable_state
from ..run_folder.variant_folders import variant_experiments
from ..support import backend, fileio
from ..support.interrupts import InterruptLatch


@dataclass
class OptimizeResult:
    folder: Path
    iterations: int = 0
    resumed_from: int = 0
    losses: list = field(default_factory=list)
    final: Path | None = None
    checkpoints: list = field(default_factory=list)
    interrupted: bool = False
    skipped: int = 0
    budget_stop: bool = False        # the time budget (optimize.seconds) ended the run early
    seconds: float = 0.0             # optimisation seconds of the whole run


def optimize(exp, iterations: int | None = None, resume: bool = False, progress=None, warn=print,
             observer=None) -> OptimizeResult:
    """Run (or continue) the optimisation of ``exp.optimize``; see the module docstring.

    ``iterations``: the run's total (default ``optimize.iterations``), checked by the command
    (:func:`psdr_cli.api.optimize`); ``progress``: optional object with ``start(total)``,
    ``advance(n, loss)``; ``warn``: one-line messages (NaN gradients, interruption); ``observer``:
    optional object whose ``iteration(exp, now, done, total, seconds, loss)`` is called on the
    loop's thread after each saved iteration (it may hold the loop there: a paused viewer,
    :mod:`psdr_cli.viewer.live`)."""
    cfg = exp.optimize
    if cfg is None:
        raise PsdrError(f"{exp.file}: optimize: missing (expected at least {{object: NAME}})")
    total = cfg.iterations if iterations is None else iterations
    check_experiment(exp)  # again: the experiment may have been changed in code after loading
    files = RunFiles(exp.run_dir)
    files.check_files()
    with lock_run(files), backend.optimization_threads():
        return _optimize(exp, files, total, resume, progress, warn, observer)


@dataclass
class RunStart:
    """What a run starts from: the saved or initial state, the inputs read and checked
    (:class:`psdr_cli.optimisation.start_state.TargetInputs`: masks included), the target images and their
    cameras (None: the scene's)."""
    state: object
    inputs: object
    targets: list
    cameras: list | None


@dataclass
class Current:
    """What a remesh replaces as the loop runs: the problem, the stage it renders against and the
    guides in use."""
    problem: Problem
    stage: Stage
    guides: GuideCache


def _optimize(exp, files: RunFiles, total: int, resume: bool, progress, warn, observer=None) -> OptimizeResult:
    """:func:`optimize` once the run folder is locked: the loop, from the saved or initial state."""
    cfg, requested = exp.optimize, total
    start = run_start(exp, files, total, resume, warn)
    exp = with_camera_mode(exp, len(start.targets))  # optimize.cameras: auto decided
    exp = with_photograph_light(exp, start.targets, start.inputs.masks)  # optimize.envmap without a probe
    it, seconds = start.state.iteration, start.state.seconds
    result = OptimizeResult(files.root, resumed_from=it)
    now, loop = start_loop(exp, start, total, warn)
    write_log(files.log, read_log(files.log, it))  # rows of unsaved iterations dropped
    if progress:
        progress.start(total, it)
    with InterruptLatch() as latch:  # a Ctrl-C that a finaliser dropped is raised again between iterations
        try:
            for it in range(start.state.iteration, total):
                latch.check()
                if cfg.seconds is not None and seconds >= cfg.seconds:
                    total = it  # the time budget is spent (a resumed run that had finished)
                    break
                t_start = time.perf_counter()
                if it in cfg.remesh.at and it > 0:
                    remesh(now, start, loop, it)
                step = iterate(now.problem, loop, now.stage, now.guides, it)
                seconds += step.t_end - t_start
                record_step(result, files, step, it, t_start, seconds, now)
                if cfg.seconds is not None and seconds >= cfg.seconds:
                    total = it + 1  # time budget spent: this is the last iteration
                save_iteration(now, files, exp, it + 1, seconds, result, last=it + 1 == total)
                if progress:
                    progress.advance(1, step.loss)
                if observer:
                    observer.iteration(exp, now, it + 1, total, seconds, step.loss)
                if it + 1 == total:
                    break
            it = total
        except KeyboardInterrupt:
            result.interrupted = True
            warn(f"interrupted during iteration {it}: {it} completed iterations are saved in {files.state}; "
                 f"continue with --resume")
            return result
        finally:
            now.problem.release()  # nothing of this run may linger in Dr.Jit's global AD graph
    return finish(exp, files, now.problem, result, RunEnd(total, requested, seconds, len(start.targets)), warn)


def run_start(exp, files: RunFiles, total: int, resume: bool, warn) -> RunStart:
    """The state a run starts from (the saved one with ``resume``, else the initial shape) and its
    targets; every input is read and checked before the run folder is touched, and a run found
    in the folder by a fresh start is moved aside, never overwritten. run.json is (re)written."""
    state = resumable_state(files, exp, total, resume, warn)
    inputs = read_targets(exp, fresh=state is None)
    if state is None:
        keep_previous_run(files, warn)
    targets, cameras, reference = load_targets(exp, files, inputs)
    if state is None:
        state = initial_state(exp, files, inputs.initial, warn, inputs.initial_values)
    fileio.write_json(files.run, run_record(exp))  # a fresh run, or the resumed one in the current version
    return RunStart(state, inputs, targets, cameras)


def start_loop(exp, start: RunStart, total: int, warn) -> tuple:
    """(the loop's :class:`Current` problem, stage and guides, its :class:`~psdr_cli.optimisation.iteration.Loop`)
    of a run from ``start``: the guides in use when a resumed run stopped are rebuilt."""
    problem = Problem.from_state(SceneSource.of(exp), start.state, start.cameras)
    engine = Engine(Settings.from_experiment(exp, loop=True))
    loop = Loop(exp.optimize, engine, total, warn, clip_factor(exp.optimize.outlier_clip, exp.scene.max_depth),
                FrozenBatch() if exp.optimize.freeze else None)
    stage = stage_of(problem, start.targets, loop.settings, loop.terms, masks=start.inputs.masks)
    return Current(problem, stage, GuideCache.resumed(problem, loop, start.state, stage)), loop


def remesh(now: Current, start: RunStart, loop, it: int):
    """The remesh at the start of iteration ``it``: a new problem, its stage and no guides."""
    now.problem = remeshed_problem(now.problem, start.cameras, it, loop.warn)
    now.stage = stage_of(now.problem, start.targets, loop.settings, loop.terms, now.stage, start.inputs.masks)
    now.guides.reset()


def record_step(result: OptimizeResult, files: RunFiles, step, it: int, t_start: float, seconds: float,
                now: Current):
    """The log row of iteration ``it``, appended to log.csv, and its loss and skip in ``result``."""
    result.skipped += int(step.skipped)
    row = log_row(it, step, t_start, seconds, now.problem, now.guides)
    result.losses.append(step.loss)
    append_log(files.log, row)


def save_iteration(now: Current, files: RunFiles, exp, iteration: int, seconds: float, result: OptimizeResult,
                   last: bool):
    """After a step (the log row is written): the problem applied, the checkpoint when due, then
    the state after ``iteration`` iterations (a kill before the state is saved repeats the
    iteration on --resume: its log row is dropped and its checkpoint rewritten, so nothing saved
    is ever missing)."""
    now.problem.apply()
    if iteration % exp.optimize.checkpoint_every == 0 or last:
        result.checkpoints.append(save_checkpoint(now.problem, files, iteration, now.stage.images, exp))
    save_state(now.problem, files, iteration, seconds, now.guides)


def log_row(it: int, step, t_start: float, seconds: float, problem, guides: GuideCache) -> dict:
    """The log.csv row of iteration ``it`` (:data:`psdr_cli.run_folder.log.LOG_FIELDS`)."""
    return {"iteration": it, "loss": f"{step.loss:.6g}", "vertices": len(problem.vertices()),
            "seconds_guiding": f"{step.t_render - step.t_guide:.4f}",
            "seconds_rendering": f"{step.t_post - step.t_render:.4f}",
            "seconds_post": f"{(step.t_guide - t_start) + (step.t_end - step.t_post):.4f}",
            "seconds_total": f"{seconds:.3f}", "skipped": int(step.skipped), "guide_bytes": guides.memory_bytes()}


def save_state(problem, files: RunFiles, iteration: int, seconds: float, guides: GuideCache):
    """The state after ``iteration`` iterations, with the shape the guides in use were built from."""
    saved = problem.export(iteration, seconds)
    if guides.snapshot is not None:
        saved.guide_V, saved.guide_values = guides.snapshot
    saved.guide_arrays = guides.arrays()
    saved.save(files.state)


def save_checkpoint(problem, files: RunFiles, iteration: int, targets, exp) -> Path:
    """Checkpoint ``iteration``: every unknown's files (:meth:`Problem.checkpoint_files`: the mesh
    iter_NNNN.ply, textures, maps, cameras) and a target | current | |difference| strip per
    preview view, at the stage's resolution (``targets``: the stage's) with pixels enlarged to the
    film's size, all written by :func:`psdr_cli.run_folder.checkpoints.write_checkpoint`."""
    with dr.suspend_grad():
        previews = {v: (targets[v], render_view(problem.scene, v, 16, seed=exp.seed))
                    for v in exp.optimize.preview_views}
    return write_checkpoint(files, iteration, problem.checkpoint_files(files, iteration), previews,
                            zoom=problem.factor)


@dataclass
class RunEnd:
    """How a run ended: the iterations done in all (the requested ones, unless the time budget
    ended it early), the requested ones, the optimisation seconds and the number of views."""
    total: int
    requested: int
    seconds: float
    views: int


def finish(exp, files: RunFiles, problem, result: OptimizeResult, end: RunEnd, warn) -> OptimizeResult:
    """The end of a run: the final mesh, the loss plot and optimize.json."""
    cfg, total, seconds = exp.optimize, end.total, end.seconds
    result.iterations, result.seconds = total, seconds
    result.budget_stop = cfg.seconds is not None and total < end.requested
    if cfg.seconds is not None and cfg.remesh.at and total < max(cfg.remesh.at) and total < end.requested:
        warn(f"the time budget ({cfg.seconds:g} s) ended the run at iteration {total}, before the remesh at "
             f"iteration {max(cfg.remesh.at)}: the final mesh has {len(problem.vertices())} vertices")
    write_mesh(files.final, dataset_coordinates(exp, problem.vertices()), problem.F, problem.uv)
    result.final = files.final
    plot_loss(files, read_log(files.log, total), PLOT_LABEL)
    fileio.write_json(files.summary, {
        "experiment": str(exp.file), "iterations": total, "resumed_from": result.resumed_from, "views": end.views,
        "final": str(files.final), "final_vertices": int(len(problem.vertices())),
        "values": problem.summary(files), "skipped_updates": result.skipped,
        "seconds": seconds})
    return result


def loop_guiding_line(label: str, run: Experiment) -> str:
    """One line: what guides the boundary terms of ``run`` in the loop (``label: ...`` for a variant);
    Mitsuba's projective integrators (``estimator.engine: mitsuba``) take no psdr guide."""
    line = "guiding none: estimator.engine mitsuba samples its own boundaries"
    if run.estimator.engine == "psdr":
        line = guiding_line(Settings.from_experiment(run, loop=True))
    return f"{label}: {line}" if label else line


def optimize_variants(exp: Experiment, labels=None, iterations: int | None = None, resume: bool = False, *,
                      progress=None, warn=print, report=None, observer=None):
    """Run every run of ``exp`` (its ``optimize.variants``, or those in ``labels``; the experiment
    itself without variants) one after another; yields (label, OptimizeResult) as each ends.

    ``progress(label)``: optional context manager factory giving each run's progress object;
    ``report``: one line per run as it starts, what guides its boundary terms in the loop;
    ``observer``: as :func:`optimize`'s, for every run."""
    if exp.optimize is None:
        raise PsdrError(f"{exp.file}: optimize: missing (expected at least {{object: NAME}})")
    for label, run in variant_experiments(exp, labels):
        if report:
            report(loop_guiding_line(label, run))
        if progress is None:
            yield label, optimize(run, iterations=iterations, resume=resume, warn=warn, observer=observer)
            continue
        with progress(label) as bar:
            result = optimize(run, iterations=iterations, resume=resume, progress=bar, warn=warn, observer=observer)
        yield label, result
