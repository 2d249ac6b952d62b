"""The Python API behind the CLI: one function per subcommand, each delegating to its module.

    render       → :func:`psdr_cli.rendering.render.render_experiment`
    grad         → :func:`psdr_cli.commands.gradient.grad_experiment` (``gradient_images``: no files)
    guide_stats  → :func:`psdr_cli.guiding.stats.guide_stats`
    compare      → :func:`psdr_cli.commands.compare.run_comparison`
    optimize     → :func:`psdr_cli.commands.optimize.optimize` (``optimize_variants``: every run of an ablation)
    evaluate     → :func:`psdr_cli.commands.evaluate.evaluate_meshes` (inputs: :func:`psdr_cli.commands.evaluate.evaluate_inputs`)
    table2       → :func:`psdr_cli.commands.evaluate.table2`
    export       → :func:`psdr_cli.commands.export.export`
    view         → :func:`psdr_cli.viewer.serve` (``live_viewer``: the observer of ``optimize --view``)

``optimize_variants`` and ``compare`` with ``ray=sweep.RayOptions(...)`` run each run / variant as a
Ray task (:mod:`psdr_cli.commands.sweep`; needs the optional extra ``psdr[ray]``).
"""
from __future__ import annotations

from pathlib import Path

from . import viewer
from .commands import compare as comparison
from .commands import evaluate as evaluation
from .commands import export as exporting
from .commands import gradient
from .commands import optimize as optimization
from .commands import sweep
from .config.experiment_file import Experiment
from .config.limits import MAX_DEPTH, MAX_ITERATIONS
from .config.options import option_count
from .errors import PsdrError
from .experiment import load
from .guiding import stats
from .rendering import estimate
from .rendering import render as rendering
from .scene.mitsuba_xml import warn_stderr
from .support import backend

#: What ``psdr evaluate --relight`` scores under (:class:`psdr_cli.commands.evaluate.Relight`).
Relight = evaluation.Relight


def load_experiment(path, warn=warn_stderr) -> Experiment:
    """Read and validate an experiment file, then its scene: a Mitsuba XML scene is read (one
    ``warn`` line per item psdr renders but cannot differentiate) and split OBJ objects are
    expanded, so that object names, views and emitters are known (:mod:`psdr_cli.experiment.load`)."""
    return load.load_experiment(path, warn)


def setup(exp: Experiment) -> str:
    """Activate the experiment's Mitsuba variant (``auto``: CUDA when present, else LLVM)."""
    return backend.activate(exp)


def render(exp: Experiment, spp: int | None = None, views=None, out: Path | None = None, progress=None):
    """``psdr render``: EXR + PNG per view in ``<output>/<name>/render/``; returns a RenderResult."""
    return rendering.render_experiment(exp, spp, views, out, progress)


def gradient_images(exp: Experiment, view: int = 0, terms=None, spp: int | None = None, min_passes: int = 1,
                    scene=None, progress=None) -> dict:
    """Forward-mode gradient images dI/dθ of one view, {term: TermEstimate}; writes nothing."""
    return estimate.gradient_images(exp, view, terms, spp, min_passes, scene, progress)


def grad(exp: Experiment, *, spp: int | None = None, terms=None, views=None, out: Path | None = None,
         fd: float | None = None, fd_spp: int | None = None, progress=None, warn=None, report=None):
    """``psdr grad``: gradient EXRs per view (and the finite-difference check); a GradResult.
    ``spp``: the interior term's samples per pixel; ``warn``: one-line warnings; ``report``: one
    line before the work, what guides each boundary term (``guiding: auto`` resolved). The
    keywords are the command's options (:class:`psdr_cli.commands.gradient.GradRequest`) and where it
    reports (:class:`psdr_cli.commands.gradient.Feedback`)."""
    request = gradient.GradRequest(spp, terms, views, out, fd, fd_spp)
    return gradient.grad_experiment(exp, request, gradient.Feedback(progress, warn, report))


def guide_stats(exp: Experiment, kinds=None, views=None, out: Path | None = None, progress=None):
    """``psdr guide-stats``: guides built with and without edge sorting; a GuideStatsResult."""
    return stats.guide_stats(exp, kinds, views, out, progress)


def compare(exp: Experiment, out: Path | None = None, progress=None, ray: "sweep.RayOptions | None" = None):
    """``psdr compare``: the experiment's ``compare:`` section; a CompareResult. With ``ray``: one
    Ray task per variant, ``progress(label)`` giving one progress object per task."""
    if ray is not None:
        return sweep.compare_sweep(exp, out, ray, progress)
    return comparison.run_comparison(exp, out, progress)


def optimize(exp: Experiment, iterations: int | None = None, resume: bool = False, progress=None, warn=print,
             observer=None):
    """``psdr optimize`` of one run (an experiment without variants, or one variant's run);
    ``observer``: e.g. a :func:`live_viewer`."""
    option_count("--iterations", iterations, 1, MAX_ITERATIONS)
    return optimization.optimize(exp, iterations=iterations, resume=resume, progress=progress, warn=warn,
                                 observer=observer)


def optimize_variants(exp: Experiment, labels=None, iterations: int | None = None, resume: bool = False, *,
                      progress=None, warn=print, ray: "sweep.RayOptions | None" = None, report=None,
                      observer=None):
    """``psdr optimize`` of every run of an experiment; yields (label, OptimizeResult). With
    ``ray``: one Ray task per run, results in the order the runs end, ``progress(label)`` giving
    one progress object (``start``, ``advance``) per run. ``report``: one line per run before it
    starts, what guides its boundary terms in the loop. ``observer``: e.g. a :func:`live_viewer`
    (not with ``ray``: the loop must run in this process)."""
    option_count("--iterations", iterations, 1, MAX_ITERATIONS)  # before any run starts, here or on Ray
    if ray is not None and observer is not None:
        raise PsdrError("--view and --ray: the viewer watches a loop running in this process; drop one")
    if ray is not None:
        return sweep.optimize_sweep(exp, labels, iterations, resume, ray, progress=progress, warn=warn, report=report)
    return optimization.optimize_variants(exp, labels, iterations, resume, progress=progress, warn=warn, report=report,
                                          observer=observer)


def evaluate(paths, reference: Path | None = None, *, samples: int | None = None, json_out: Path | None = None,
             report: Path | None = None, progress=None, align: str = "auto", relight=None, max_depth: int | None = None):
    """``psdr evaluate``: distances of meshes / run checkpoints to the reference; an EvaluateResult
    (for an experiment with a camera dataset: held-out view scores, a HeldOutReport; ``align``:
    whether the held-out cameras are fitted first: auto (when the run refined its cameras), on, off;
    ``max_depth``: the held-out renders' path depth, default each run's;
    ``relight``: an :class:`psdr_cli.commands.evaluate.Relight`, to score the runs under other light instead)."""
    option_count("--max-depth", max_depth, 1, MAX_DEPTH)
    dataset = evaluation.dataset_experiment(paths)
    if max_depth is not None and relight is not None:
        raise PsdrError("--max-depth: not with --relight (it sets the depth of the held-out views' renders)")
    if max_depth is not None and dataset is None:
        raise PsdrError("--max-depth: only for the held-out views of a camera-dataset experiment (psdr evaluate cfg.yaml)")
    if relight is not None:
        return evaluation.evaluate_relit(dataset, relight, json_out, progress)
    if dataset is not None:
        return evaluation.evaluate_held_out(dataset, reference, samples, json_out, progress, align, max_depth)
    inputs = evaluation.evaluate_inputs(paths, reference, samples, report)
    return evaluation.evaluate_meshes(inputs, json_out, progress)


def table2(experiments: list, out: Path) -> Path:
    """``psdr table2``: the paper's Table 2 for finished runs, written to ``out``."""
    return evaluation.table2(experiments, out)


def export(source, out: Path | None = None, texture: Path | None = None, warn=print):
    """``psdr export``: a run folder or mesh file as OBJ + MTL + PNG and binary glTF (and the
    rotated environment map of a run that recovered its rotation); an ExportResult."""
    return exporting.export(source, out, texture, warn)


def live_viewer(host: str = "127.0.0.1", port: int = 8080, warn=print, interval: float = 1.0):
    """The web viewer of a running optimisation (``psdr optimize --view``), serving on
    ``host:port`` at once; pass it as ``observer``. Needs the optional extra ``psdr[view]``."""
    return viewer.live_viewer(host, port, warn, interval)


def view(path, host: str = "127.0.0.1", port: int = 8080, seconds: float | None = None, warn=print, ready=print):
    """``psdr view``: a run folder (read-only, while it runs or after) or a mesh file in the web
    viewer, until Ctrl-C or for ``seconds``; ``ready(url)`` once it serves."""
    return viewer.serve(path, host, port, seconds, warn=warn, ready=ready)
