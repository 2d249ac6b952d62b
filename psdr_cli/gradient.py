"""``psdr grad``: the gradient images of an experiment's views, term by term, written as EXR and
PNG, with an optional finite-difference check (``--fd``) and its verdict; the estimate itself is
:mod:`psdr_cli.estimate`.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import mitsuba as mi
import numpy as np

from . import fileio
from .config import Experiment, option_number, option_spp, parse_terms, parse_views
from .errors import PsdrError
from .estimate import forward_gradient, guiding_line, make_guides, prepare
from .parameters import Parameter
from .reference import agreement, fd_resolution, finite_difference
from .render import render_view
from .shading import smooth_warning


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
    (against 1 / the largest axis rate)."""
    kind = parameter.config.kind
    if kind == "translate":
        box = scene.mi_scene.bbox()
        size = float(np.linalg.norm(np.subtract(box.max, box.min)))
        what = f"the scene's size {size:.3g} (its bounding-box diagonal, in scene units)"
    elif kind == "scale":
        size = 1.0 / max(float(np.max(np.abs(parameter.config.axis))), 1e-30)
        what = f"{size:.3g} (1 / the largest axis rate)"
    else:
        size, what = 1.0, "1 radian"
    lo, hi = FD_STEP[0] * size, FD_STEP[1] * size
    if not lo <= h <= hi:
        raise PsdrError(f"--fd: step {h:g} is not small against the scene for a {kind} (expected "
                        f"{lo:.3g} to {hi:.3g}: {FD_STEP[0]:g} to {FD_STEP[1]:g} × {what})")


def grad_experiment(exp: Experiment, spp: int | None = None, terms=None, views=None, out: Path | None = None,
         fd: float | None = None, fd_spp: int | None = None, progress=None, warn=None, report=None) -> GradResult:
    """Gradient images of every requested view to ``<output>/<name>/grad/view_XXX.exr``.

    Channels: the render (R, G, B), one group per term (``interior.R`` …) and ``total.*``; with
    ``fd = h`` also central finite differences ``fd.*`` (common random numbers, 8 batches of
    ``fd_spp`` samples per pixel in total, default 4 × the interior spp) and the agreement
    statistics. PNG previews use a diverging colour map shared by all terms. ``report`` gets one
    line first: what guides each boundary term."""
    guided_by = guiding_line(exp, terms)
    if report:
        report(guided_by)
    option_number("--fd", fd)
    option_spp("--interior-spp", spp, exp.scene.width, exp.scene.height)
    option_spp("--fd-spp", fd_spp, exp.scene.width, exp.scene.height)
    if fd_spp is not None and fd_spp < FD_BATCHES:
        raise PsdrError(f"--fd-spp: expected at least {FD_BATCHES} samples per pixel ({FD_BATCHES} batches), got {fd_spp}")
    terms = parse_terms(terms) or exp.estimator.terms
    views = parse_views(views, len(exp.scene.cameras))
    scene, parameter, edges, settings = prepare(exp, spp)
    if fd:
        check_fd_step(fd, scene, parameter)
    variant = mi.variant()
    for message in (smooth_warning(scene),) if warn else ():
        if message:
            warn(message)
    fd_spp = fd_spp or 4 * settings.spp
    min_passes = FD_BATCHES if fd else 1
    folder = fileio.writable_folder(exp.command_dir("grad", out))
    for v in views:  # before the work: a folder or device there is refused now, not after it
        fileio.check_output_file(folder / f"view_{v:03d}.exr")
    result = GradResult(folder, views, parameter.name, variant=variant)
    if progress:
        per_view = sum(settings.samples(t) for t in terms) + (2 * fd_spp if fd else 0)
        progress.start(len(views) * per_view)
    for v in views:
        t0 = time.perf_counter()
        guides = make_guides(scene, edges, [v], terms, settings, parameter)
        guide_seconds = time.perf_counter() - t0
        estimates = {t: forward_gradient(scene, edges, parameter, v, t, settings, min_passes,
                                         progress=progress.advance if progress else None, guides=guides)
                     for t in terms}
        image = estimates["interior"].primal if "interior" in estimates else \
            render_view(scene, v, settings.spp, seed=exp.seed)
        total = sum(e.gradient for e in estimates.values())
        channels = {"R": image[..., 0], "G": image[..., 1], "B": image[..., 2]}
        for name, g in [(t, e.gradient) for t, e in estimates.items()] + [("total", total)]:
            for c, ch in enumerate("RGB"):
                channels[f"{name}.{ch}"] = g[..., c]
        header = {"psdr.experiment": str(exp.file), "psdr.view": str(v), "psdr.parameter": parameter.name,
                  "psdr.terms": ",".join(terms), "psdr.sampling": settings.sampling,
                  "psdr.guiding": guided_by, "psdr.edge_sort": str(settings.edge_sort),
                  "psdr.guide_seconds": f"{guide_seconds:.3f}",
                  "psdr.spp": {t: str(settings.samples(t)) for t in terms},
                  "psdr.seconds": {t: f"{e.seconds:.3f}" for t, e in estimates.items()}}
        stats = None
        if fd:
            batches = finite_difference(scene, parameter, v, fd, fd_spp, seed=exp.seed, batches=FD_BATCHES,
                                        progress=progress.advance if progress else None)
            fd_image = np.mean(batches, axis=0)
            for c, ch in enumerate("RGB"):
                channels[f"fd.{ch}"] = fd_image[..., c]
            stats = agreement([(e.passes, e.weights) for e in estimates.values()], batches,
                              resolution=fd_resolution(image, fd, fd_spp, FD_BATCHES))
            header["psdr.fd_h"] = str(fd)
            header["psdr.fd_spp"] = str(fd_spp)
        exr = folder / f"view_{v:03d}.exr"
        fileio.write_exr(exr, {k: np.asarray(x, np.float32) for k, x in channels.items()}, header)
        scale = float(np.percentile(np.abs(total.mean(-1)), 99.5)) or 1.0
        fileio.write_preview(folder / f"view_{v:03d}.png", image)
        previews = [(t, e.gradient) for t, e in estimates.items()] + [("total", total)]
        if fd:
            previews.append(("fd", fd_image))
        for name, g in previews:
            fileio.write_gradient_preview(folder / f"view_{v:03d}_{name}.png", g, scale)
        result.files.append(exr)
        result.seconds.append({**({"guiding": guide_seconds} if guides.all() else {}),
                               **{t: e.seconds for t, e in estimates.items()}})
        result.sums.append({**{t: float(e.gradient.sum()) for t, e in estimates.items()}, "total": float(total.sum())})
        result.agreement.append(stats)
    fileio.write_json(folder / "summary.json", {
        "experiment": str(exp.file), "parameter": result.parameter, "variant": variant, "terms": list(terms),
        "spp": {t: settings.samples(t) for t in terms}, "sampling": settings.sampling, "fd_h": fd,
        "guiding": settings.guiding, "edge_sort": settings.edge_sort,
        "views": [{"view": v, "file": str(f), "seconds": s, "sums": m, "fd_agreement": a}
                  for v, f, s, m, a in zip(views, result.files, result.seconds, result.sums, result.agreement)]})
    return result
