"""The interface every term of dI/dθ implements, like Mitsuba 3's integrators share one signature.

A term is a :class:`Term`: its name (the word in ``estimator.terms``), the estimator key holding
its samples per pixel, its random-number stream, whether a guide can serve it, and ``estimate``,
which computes one pass:

    estimate(scene, edges, view, spp, seed, estimator, max_depth, *, guide=None) -> mi.Float

``scene`` is a :class:`psdr_cli.scene.build.Scene` or anything with its ``mi_scene``, ``sensors`` and
``resolution`` (W, H); its AD state (θ or vertex gradients) is set before the call. ``edges`` are
the boundary edges, ``spp`` the samples per pixel of this pass, ``seed`` its sampler seed,
``estimator`` the experiment's :class:`psdr_cli.config.EstimatorConfig`, ``max_depth`` the scene's
path depth and ``guide`` the term's guide (None: unguided). The result is a flat W·H·3 image
attached to the AD graph: the interior term's primal value is the rendered image, a boundary
term's primal value is 0 (it only carries derivatives).

A term may also trace one pass of several views as one wavefront (fewer, wider kernels and one
trace of its Python code instead of one per view):

    estimate_views(scene, edges, views, spp, seed, estimator, max_depth) -> [mi.Float per view]

with the samples of ``estimate`` drawn from one sampler seeded with ``seed`` (unguided terms only).
``views`` may name a view more than once (forward mode traces several passes of one view so):
each entry must then be an independent estimate from its own lanes, so a term must not key its
random numbers or any cached state on the view's index.

Each estimator module declares its ``TERM``; :mod:`.registry` lists them.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import mitsuba as mi

from .passes import make_sampler


@dataclass(frozen=True)
class GuideTarget:
    """What the guides of a boundary term need from it (:mod:`psdr_cli.guiding.targets`,
    ``psdr guide-stats``):

        techniques(sampling) -> the techniques that get a guide each, in the order of their seeds
        evaluate(scene, sensors, draw, technique, u, sampler, max_depth, *, mis) -> F̃(u)
        motion(scene, sensors, draw, technique, u, *, mis) -> [v per view]   (optional)

    ``evaluate`` is the guide's target at primary samples u (mi.Point3f) summed over the views'
    ``sensors`` (``draw``: the edges, their positions and distribution,
    :class:`.boundary_sampling.EdgeDraw`; ``sampler``: a fresh one per batch when ``random``, else
    None; ``mis``: whether the techniques are combined by MIS); ``motion``, when
    given, is the integrand with θ's velocity (forward mode: the target becomes Σ max |dv/dθ|).
    The guide of technique i is built with seed + ``seed_offset`` + i; scenes whose ``max_depth``
    is below ``min_depth`` have no such paths (unguided). The term reads {technique: guide} when
    ``per_technique``, else its one guide; ``loop_fed``: the optimisation loop fits its guides to
    the samples of its own passes when the guide kind is loop-fed (:mod:`psdr_cli.guiding.kinds`)."""
    techniques: Callable[[str], tuple]
    evaluate: Callable[..., mi.Float]
    motion: Callable[..., list] | None = None
    seed_offset: int = 0
    min_depth: int = 1
    random: bool = False
    per_technique: bool = True
    loop_fed: bool = False


@dataclass(frozen=True)
class Term:
    """One term of dI/dθ (module docstring)."""
    name: str
    samples_key: str      # EstimatorConfig field with its samples per pixel (spp, primary_spp, boundary_spp)
    stream: int           # random-number stream of its passes (estimators.passes.pass_seed)
    estimate: Callable[..., mi.Float]
    guide: GuideTarget | None = None   # how a boundary guide serves it (None: no guide can)
    #: one pass for several views traced as one wavefront (None: one view at a time), see above
    estimate_views: Callable[..., list] | None = None
    #: whether its primal value is the rendered image (the others' is 0)
    renders: bool = False
    #: whether its passes read the intersection curves among the meshes (searched ahead of them)
    reads_intersections: bool = False

    @property
    def guided(self) -> bool:
        """Whether a boundary guide can serve the term."""
        return self.guide is not None


def boundary_pass(scene, edges, spp: int, seed: int, views: int = 1):
    """(N, sampler, P) of one boundary pass: N = spp · W · H samples per view, their sampler (as
    wide as ``views`` views' samples) and the AD vertex buffer of the edge objects (None without
    edges)."""
    width, height = scene.resolution
    n = spp * width * height
    sampler = make_sampler(seed, n * views)
    P = edges.positions(mi.traverse(scene.mi_scene)) if edges.count else None
    return n, sampler, P
