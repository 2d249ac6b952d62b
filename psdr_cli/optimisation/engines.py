"""The renderer behind an optimisation's AD images (``estimator.engine``).

``psdr``: our estimators, I = interior + Σ boundary terms (:func:`psdr_cli.rendering.estimate.ad_image`).

``mitsuba``: Mitsuba 3's own projective-sampling integrators (Zhang et al. 2023) as Mitsuba's
shape-optimisation tutorial configures them: ``direct_projective`` (one bounce, max_depth 2) or
``prb_projective`` (``max_depth`` of the scene), the indirect-visibility (shadow) term off
(``sppi = 0``) unless ``mitsuba_shadows``, emitters visible (``hide_emitters = false``, the
tutorial's setting; the targets show them too) and ``mitsuba_spp`` samples per pixel (16):

    I_v = mi.render(scene, params, sensor=v, spp=mitsuba_spp, seed=s(seed, v, iteration)),

whose reverse-mode derivative is Mitsuba's. Both give a flat W·H·3 image attached to the AD
graph of the optimised vertices, so the optimisation loop around them is the same.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from ..config.estimator_section import EstimatorConfig
from ..estimators.coverage import coverage_image
from ..estimators.passes import pass_seed
from ..estimators.registry import COVERAGE_STREAMS, MITSUBA_STREAM
from ..rendering import estimate
from ..rendering.estimate import Settings


def mitsuba_integrator_name(est: EstimatorConfig, max_depth: int) -> str:
    """``mitsuba_integrator``, or by default ``direct_projective`` for max_depth ≤ 2 (direct light
    only) and ``prb_projective`` for deeper paths."""
    if est.mitsuba_integrator:
        return est.mitsuba_integrator
    return "direct_projective" if max_depth <= 2 else "prb_projective"


def mitsuba_integrator(est: EstimatorConfig, max_depth: int):
    """Mitsuba's projective integrator with the shape-optimisation tutorial's options."""
    name = mitsuba_integrator_name(est, max_depth)
    props = {"type": name, "hide_emitters": False}
    if not est.mitsuba_shadows:
        props["sppi"] = 0  # no indirect-visibility (shadow) discontinuities: the recipe's setting
    if name == "prb_projective":
        props["max_depth"] = max_depth
    integrator = mi.load_dict(props)
    # its advice to set the film's sample_border is moot: our box filter has no border to sample
    integrator.sample_border_warning = False
    return integrator


def mitsuba_image(scene, params, integrator, view: int, spp: int, seed: int) -> mi.Float:
    """Mitsuba's render of camera ``view`` (flat W·H·3, AD through ``params``)."""
    image = mi.render(scene.mi_scene, params, sensor=scene.sensors[view], integrator=integrator,
                      spp=spp, seed=seed)
    return dr.ravel(image)


class Engine:
    """The AD image of one view in one iteration, by psdr's estimators or by Mitsuba.

    ``settings`` are the loop's, as the engine uses them: Mitsuba's integrators sample their own
    boundaries, so under ``estimator.engine: mitsuba`` no psdr guide is built (``guiding: none``).
    The terms are the estimator's (``settings.estimator.terms``)."""

    def __init__(self, settings: Settings):
        est = settings.estimator
        self.name = est.engine
        self.settings = settings if self.needs_edges else settings.with_estimator(guiding="none")
        self.terms = tuple(est.terms)
        self.integrator = mitsuba_integrator(est, settings.max_depth) if self.name == "mitsuba" else None

    @property
    def needs_edges(self) -> bool:
        """psdr samples the boundary terms on its own edge list; Mitsuba finds its own."""
        return self.name == "psdr"

    def image(self, problem, edges, view: int, iteration: int, guides=None) -> mi.Float:
        """I_v of ``iteration`` for the current shape of ``problem`` (flat W·H·3, AD)."""
        if self.name == "mitsuba":
            seed = pass_seed(self.settings.seed, view, iteration, MITSUBA_STREAM)
            return mitsuba_image(problem.scene, problem.params, self.integrator, view,
                                 self.settings.estimator.mitsuba_spp, seed)
        return estimate.ad_image(problem.scene, edges, view, self.terms, self.settings, pass_index=iteration,
                                 guides=guides)

    def images(self, problem, edges, views, iteration: int, guides=None, terms=None) -> list:
        """:meth:`image` of each of ``views``; psdr's terms that can trace the views as one
        wavefront do (:func:`psdr_cli.rendering.estimate.ad_images`), unless the cameras move (a wavefront
        holds each lane's camera as constants). ``terms``: a part of psdr's terms (default: all
        of them)."""
        if self.name == "mitsuba":
            if terms is not None:
                raise ValueError("Engine.images: Mitsuba's integrators render every term at once")
            return [self.image(problem, edges, v, iteration, guides) for v in views]
        moving = problem.cameras is not None and problem.cameras.attached
        return estimate.ad_images(problem.scene, edges, views, self.terms if terms is None else terms,
                                  self.settings, pass_index=iteration, guides=guides, one_by_one=moving)

    def coverage(self, problem, edges, view: int, iteration: int) -> mi.Float:
        """C_v of ``iteration``: the rendered coverage of a masked view (flat W·H, AD;
        :mod:`psdr_cli.estimators.coverage`), by psdr's estimators whatever the engine."""
        est = self.settings.estimator
        seeds = tuple(pass_seed(self.settings.seed, view, iteration, s) for s in COVERAGE_STREAMS)
        return coverage_image(problem.scene, edges, problem.cfg.object, view, seeds, est, spp=est.spp,
                              primary_spp=est.primary_spp)
