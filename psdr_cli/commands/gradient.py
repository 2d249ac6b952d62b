"""``psdr grad``: the gradient images of an experiment's views, term by term, written as EXR and
PNG, with an optional finite-difference check (``--fd``) and its verdict; the estimate itself is
:mod:`psdr_cli.rendering.estimate`.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import mitsuba as mi
import numpy as np

from ..config.experiment_file import Experiment
from ..config.options import option_number, option_spp, parse_terms, parse_views
from ..errors import PsdrError
from ..estimators import registry
from ..geometry.parameters import Parameter
from ..geometry.shading import smooth_warning
from ..rendering.estimate import Settings, forward_gradient, guiding_line, make_guides, prepare
from ..rendering.reference import agreement, fd_resolution, finite_difference
from ..rendering.render import render_view
from ..support import fileio


@dataclass
class GradResult:
    folder: Path
    views: list
    parameter: str = ""
    files: list = field(default_factory=list)
    seconds: list = field(default_factory=list)      # per view: {term: seconds}
    sums: list = field(default_factory=list)         # per view: {term: image sum}
    agreement: list = field(default_factory=list)    # per view: FD agreement (with --fd)
    variant: str = ""


#: Independent batches of the estimate and of the finite differences behind the --fd statistics.
FD_BATCHES = 8


#: Finite-difference steps ``--fd h`` must move the scene by between FD_STEP[0] and FD_STEP[1] of
#: its size: at most a tenth (central differences need a small step), at least what float32
#: positions resolve.
FD_STEP = (1e-6, 0.1)


def check_fd_step(h: float, scene, parameter: Parameter):
    """Refuse a step ``h`` that is not small against the scene: in scene units for a translation
    (against the diagonal of the scene's bounding box), radians for a rotation, a rate for a scale
    (against 1 / the largest axis rate), the log of the focal scale for a camera's focal length."""
    kind = parameter.config.kind
    if kind == "translate":
        box = scene.mi_scene.bbox()
        size = float(np.linalg.norm(np.subtract(box.max, box.min)))
        what = f"the scene's size {size:.3g} (its bounding-box diagonal, in scene units)"
    elif kind == "scale":
        size = 1.0 / max(float(np.max(np.abs(parameter.config.axis))), 1e-30)
        what = f"{size:.3g} (1 / the largest axis rate)"
    elif kind == "focal":
        size, what = 1.0, "1 (θ = log of the focal scale)"
    else:
        size, what = 1.0, "1 radian"
    lo, hi = FD_STEP[0] * size, FD_STEP[1] * size
    if not lo <= h <= hi:
        raise PsdrError(f"--fd: step {h:g} is not small against the scene for a {kind} (expected "
                        f"{lo:.3g} to {hi:.3g}: {FD_STEP[0]:g} to {FD_STEP[1]:g} × {what})")


@dataclass
class GradRequest:
    """What ``psdr grad`` is asked for: the interior term's samples per pixel (None:
    ``estimator.spp``), the terms and views (as given on the command line; None: the experiment's
    terms, every view), the output folder (None: the experiment's) and the finite-difference
    check: its step h (None: no check) and samples per pixel (None: 4 × the interior spp)."""
    spp: int | None = None
    terms: object = None
    views: object = None
    out: Path | None = None
    fd: float | None = None
    fd_spp: int | None = None


@dataclass
class Feedback:
    """Where ``psdr grad`` reports while it works: ``progress`` (``start(total)``,
    ``advance(n)``), ``warn`` (one-line warnings) and ``report`` (one line before the work)."""
    progress: object = None
    warn: object = None
    report: object = None


@dataclass
class GradPlan:
    """A checked request: the terms and views, the finite-difference step (None: no check) and
    its samples per pixel, the output folder and the line saying what guides each boundary term."""
    terms: tuple
    views: list
    fd: float | None
    fd_spp: int
    folder: Path
    guided_by: str


@dataclass
class ViewGradient:
    """The gradient of one view: its render, the estimate of each term and their total, the
    seconds spent building its guides (and whether any was built) and, with ``--fd``, the mean
    finite differences and their agreement with the estimate."""
    view: int
    image: np.ndarray
    estimates: dict
    total: np.ndarray
    guide_seconds: float
    guided: bool
    fd_image: np.ndarray | None = None
    agreement: dict | None = None


def grad_experiment(exp: Experiment, request: GradRequest, feedback: Feedback | None = None) -> GradResult:
    """Gradient images of every requested view to ``<output>/<name>/grad/view_XXX.exr``.

    Channels: the render (R, G, B), one group per term (``interior.R`` …) and ``total.*``; with
    ``fd = h`` also central finite differences ``fd.*`` (common random numbers, 8 batches of
    ``fd_spp`` samples per pixel in total, default 4 × the interior spp) and the agreement
    statistics. PNG previews use a diverging colour map shared by all terms. ``feedback.report``
    gets one line first: what guides each boundary term."""
    feedback = feedback or Feedback()
    guided_by = guiding_line(Settings.from_experiment(exp), request.terms)
    if feedback.report:
        feedback.report(guided_by)
    check_request(exp, request)
    terms = parse_terms(request.terms) or exp.estimator.terms
    views = parse_views(request.views, len(exp.scene.cameras))
    setup = prepare(exp, request.spp)
    if request.fd:
        check_fd_step(request.fd, setup.scene, setup.parameter)
    variant = mi.variant()
    warn_smooth(setup.scene, feedback.warn)
    plan = GradPlan(terms, views, request.fd, request.fd_spp or 4 * setup.settings.spp,
                    output_folder(exp, request.out, views), guided_by)
    result = GradResult(plan.folder, views, setup.parameter.name, variant=variant)
    if feedback.progress:
        feedback.progress.start(len(views) * samples_per_view(setup.settings, plan))
    for v in views:
        view = view_gradient(exp, setup, plan, v, feedback.progress)
        result.files.append(write_view(exp, setup, plan, view))
        add_view(result, view)
    write_summary(exp, setup.settings, plan, result)
    return result


def check_request(exp: Experiment, request: GradRequest):
    """The command-line values of ``request``: the step, the interior and the finite-difference
    samples per pixel (at least one per batch)."""
    option_number("--fd", request.fd)
    option_spp("--interior-spp", request.spp, exp.scene.width, exp.scene.height)
    option_spp("--fd-spp", request.fd_spp, exp.scene.width, exp.scene.height)
    if request.fd_spp is not None and request.fd_spp < FD_BATCHES:
        raise PsdrError(f"--fd-spp: expected at least {FD_BATCHES} samples per pixel ({FD_BATCHES} batches), "
                        f"got {request.fd_spp}")


def warn_smooth(scene, warn):
    """The warning for smooth-shaded transmitting objects, when ``warn`` is given and it applies."""
    message = smooth_warning(scene) if warn else None
    if message:
        warn(message)


def output_folder(exp: Experiment, out: Path | None, views: list) -> Path:
    """The grad folder, writable, with none of the views' EXR paths blocked (checked before the
    work: a folder or device there is refused now, not after it)."""
    folder = fileio.writable_folder(exp.command_dir("grad", out))
    for v in views:
        fileio.check_output_file(folder / f"view_{v:03d}.exr")
    return folder


def samples_per_view(settings, plan: GradPlan) -> int:
    """Samples per pixel of one view: every term's, and both sides of the finite differences."""
    return sum(settings.samples(t) for t in plan.terms) + (2 * plan.fd_spp if plan.fd else 0)


def view_gradient(exp: Experiment, setup, plan: GradPlan, v: int, progress) -> ViewGradient:
    """The guides, every term's forward-mode estimate and (with ``--fd``) the finite differences
    of view ``v``, in this order (each draws from its own random stream)."""
    scene, parameter, edges, settings = setup
    advance = progress.advance if progress else None
    t0 = time.perf_counter()
    guides = make_guides(scene, edges, [v], plan.terms, settings, parameter)
    guide_seconds = time.perf_counter() - t0
    min_passes = FD_BATCHES if plan.fd else 1
    estimates = {t: forward_gradient(scene, edges, parameter, v, t, settings, min_passes, progress=advance,
                                     guides=guides) for t in plan.terms}
    rendered = [e.primal for t, e in estimates.items() if registry.term(t).renders]
    image = rendered[0] if rendered else render_view(scene, v, settings.spp, seed=exp.seed)
    total = sum(e.gradient for e in estimates.values())
    view = ViewGradient(v, image, estimates, total, guide_seconds, bool(guides.all()))
    if plan.fd:
        batches = finite_difference(scene, parameter, v, plan.fd, plan.fd_spp, seed=exp.seed, batches=FD_BATCHES,
                                    progress=advance)
        view.fd_image = np.mean(batches, axis=0)
        view.agreement = agreement([(e.passes, e.weights) for e in estimates.values()], batches,
                                   resolution=fd_resolution(image, plan.fd, plan.fd_spp, FD_BATCHES))
    return view


def view_channels(view: ViewGradient) -> dict:
    """The EXR channels of a view: R, G, B of the render, ``TERM.R`` … per term, ``total.*`` and
    (with ``--fd``) ``fd.*``."""
    channels = {"R": view.image[..., 0], "G": view.image[..., 1], "B": view.image[..., 2]}
    for name, g in [(t, e.gradient) for t, e in view.estimates.items()] + [("total", view.total)]:
        for c, ch in enumerate("RGB"):
            channels[f"{name}.{ch}"] = g[..., c]
    if view.fd_image is not None:
        for c, ch in enumerate("RGB"):
            channels[f"fd.{ch}"] = view.fd_image[..., c]
    return channels


def view_header(exp: Experiment, setup, plan: GradPlan, view: ViewGradient) -> dict:
    """The EXR header of a view: the experiment, θ, terms, sampling, guiding, samples and seconds
    (and the finite-difference step and samples)."""
    settings, terms = setup.settings, plan.terms
    header = {"psdr.experiment": str(exp.file), "psdr.view": str(view.view), "psdr.parameter": setup.parameter.name,
              "psdr.terms": ",".join(terms), "psdr.sampling": settings.sampling,
              "psdr.guiding": plan.guided_by, "psdr.edge_sort": str(settings.edge_sort),
              "psdr.guide_seconds": f"{view.guide_seconds:.3f}",
              "psdr.spp": {t: str(settings.samples(t)) for t in terms},
              "psdr.seconds": {t: f"{e.seconds:.3f}" for t, e in view.estimates.items()}}
    if plan.fd:
        header["psdr.fd_h"] = str(plan.fd)
        header["psdr.fd_spp"] = str(plan.fd_spp)
    return header


def write_view(exp: Experiment, setup, plan: GradPlan, view: ViewGradient) -> Path:
    """``view_XXX.exr`` and its PNG previews: the render, and each term's gradient, the total's
    (and the finite differences') with one diverging scale, the 99.5th percentile of |total|."""
    v, folder = view.view, plan.folder
    exr = folder / f"view_{v:03d}.exr"
    fileio.write_exr(exr, {k: np.asarray(x, np.float32) for k, x in view_channels(view).items()},
                     view_header(exp, setup, plan, view))
    scale = float(np.percentile(np.abs(view.total.mean(-1)), 99.5)) or 1.0
    fileio.write_preview(folder / f"view_{v:03d}.png", view.image)
    previews = [(t, e.gradient) for t, e in view.estimates.items()] + [("total", view.total)]
    if view.fd_image is not None:
        previews.append(("fd", view.fd_image))
    for name, g in previews:
        fileio.write_gradient_preview(folder / f"view_{v:03d}_{name}.png", g, scale)
    return exr


def add_view(result: GradResult, view: ViewGradient):
    """The seconds, sums and agreement of a view, appended to ``result``."""
    estimates = view.estimates
    result.seconds.append({**({"guiding": view.guide_seconds} if view.guided else {}),
                           **{t: e.seconds for t, e in estimates.items()}})
    result.sums.append({**{t: float(e.gradient.sum()) for t, e in estimates.items()}, "total": float(view.total.sum())})
    result.agreement.append(view.agreement)


def write_summary(exp: Experiment, settings, plan: GradPlan, result: GradResult):
    """``summary.json``: the run's settings and, per view, its file, seconds, sums and agreement."""
    fileio.write_json(plan.folder / "summary.json", {
        "experiment": str(exp.file), "parameter": result.parameter, "variant": result.variant,
        "terms": list(plan.terms), "spp": {t: settings.samples(t) for t in plan.terms},
        "sampling": settings.sampling, "fd_h": plan.fd, "guiding": settings.guiding, "edge_sort": settings.edge_sort,
        "views": [{"view": v, "file": str(f), "seconds": s, "sums": m, "fd_agreement": a}
                  for v, f, s, m, a in zip(result.views, result.files, result.seconds, result.sums, result.agreement)]})
