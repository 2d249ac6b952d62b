"""Gradient images: every term of dI/dθ = interior + primary + direct + indirect, in passes.

``term_image`` is the one dispatcher from a term name to its estimator. It returns a flat
W·H·3 AD image for one pass: the interior term's primal value is the rendered image, the
boundary terms' primal value is 0 (they only carry derivatives). The same images serve forward
mode (θ → gradient image, :func:`forward_gradient`) and reverse mode (image loss → scene
parameters, :func:`ad_image` + ``dr.backward``).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import drjit as dr
import mitsuba as mi
import numpy as np

from .estimators import interior
from .estimators.boundary_sampling import BoundaryEdges
from .estimators.direct import direct_boundary
from .estimators.indirect import indirect_boundary
from .estimators.primary import primary_boundary
from .render import camera_rays, make_sampler, pass_seed

TERMS = ("interior", "primary", "direct", "indirect")
#: Upper bound on the lanes of one differentiable pass (AD graphs are larger than primal ones).
AD_LANES = 1 << 20


@dataclass
class Settings:
    """Sample counts (per pixel) and techniques of one gradient estimate."""
    spp: int = 64
    primary_spp: int = 16
    boundary_spp: int = 16
    sampling: str = "mis"
    passes: int = 1
    max_depth: int = 3
    seed: int = 0
    guiding: str = "none"
    edge_sort: bool = False
    estimator: object = None  # the experiment's EstimatorConfig (guide parameters)

    @staticmethod
    def from_experiment(exp, spp: int | None = None) -> "Settings":
        e = exp.estimator
        return Settings(spp=spp or e.spp, primary_spp=e.primary_spp, boundary_spp=e.boundary_spp,
                        sampling=e.sampling, passes=e.passes, max_depth=exp.scene.max_depth, seed=exp.seed,
                        guiding=e.guiding, edge_sort=e.edge_sort, estimator=e)

    def samples(self, term: str) -> int:
        """Samples per pixel of ``term``."""
        return {"interior": self.spp, "primary": self.primary_spp}.get(term, self.boundary_spp)


def term_passes(term: str, settings: Settings, pixels: int, min_passes: int = 1) -> list[int]:
    """Samples per pixel of each pass: at least ``max(passes, min_passes)`` passes, each of at
    most ``AD_LANES`` lanes."""
    spp = settings.samples(term)
    n = max(settings.passes, min_passes, math.ceil(spp * pixels / AD_LANES))
    n = min(n, spp)
    base, extra = divmod(spp, n)
    return [base + (1 if i < extra else 0) for i in range(n)]


def interior_image(scene, sensor, spp: int, seed: int, max_depth: int):
    """Mean of ``spp`` material-form path samples per pixel (flat W·H·3, AD)."""
    width, height = sensor.film().size()
    sampler = make_sampler(seed, width * height * spp)
    ray, weight = camera_rays(sensor, sampler, width, height, spp)
    L = weight * interior.radiance(scene, sampler, ray, max_depth, ad=True)
    return dr.ravel(mi.Color3f([dr.block_sum(L[c], spp) / spp for c in range(3)]))


def make_guides(scene, edges: BoundaryEdges, views, terms, settings: Settings):
    """Guides of the direct and indirect terms for ``views`` (empty when guiding is off)."""
    from .guiding.targets import Guides, build_guides
    if settings.guiding == "none" or settings.estimator is None:
        return Guides()
    est = settings.estimator
    if est.guiding != settings.guiding:
        from dataclasses import replace
        est = replace(est, guiding=settings.guiding)
    return build_guides(scene, edges, list(views), terms, settings.sampling, settings.max_depth, est,
                        settings.seed)


def term_image(scene, edges: BoundaryEdges, view: int, term: str, spp: int, seed: int,
               settings: Settings, guides=None):
    """One pass of ``term`` for camera ``view`` with ``spp`` samples per pixel (flat W·H·3, AD).

    ``scene`` is a :class:`psdr_cli.scene.Scene`; its AD state (θ or vertex gradients) must be
    set before the call. ``guides`` (:class:`psdr_cli.guiding.targets.Guides`) guide the
    direct and indirect terms."""
    mi_scene, sensor = scene.mi_scene, scene.sensors[view]
    width, height = scene.resolution
    if term == "interior":
        return interior_image(mi_scene, sensor, spp, seed, settings.max_depth)
    n = spp * width * height
    sampler = make_sampler(seed, n)
    P = edges.positions(mi.traverse(mi_scene)) if edges.count else None
    if term == "primary":
        return primary_boundary(mi_scene, sensor, edges, P, n, sampler, settings.max_depth)
    if term == "direct":
        return direct_boundary(mi_scene, sensor, edges, P, n, sampler, settings.sampling,
                               guides.direct if guides else None)
    if term == "indirect":
        return indirect_boundary(mi_scene, sensor, edges, P, n, sampler, settings.max_depth,
                                 guides.indirect if guides else None)
    raise ValueError(f"unknown term {term!r}")


def stream(term: str) -> int:
    """Random-number stream of a term (terms never share samples)."""
    return 1 + TERMS.index(term)


@dataclass
class TermEstimate:
    """Forward-mode result of one term: mean gradient image and the per-pass images."""
    term: str
    gradient: np.ndarray
    passes: list = field(default_factory=list)
    weights: list = field(default_factory=list)
    seconds: float = 0.0
    primal: np.ndarray | None = None

    def standard_error(self) -> np.ndarray | None:
        """Per-pixel standard error of the mean from the spread of the passes (≥ 2 passes)."""
        from .reference import mean_and_error
        return mean_and_error(self.passes, self.weights)[1] if len(self.passes) > 1 else None


def forward_gradient(scene, edges, parameter, view: int, term: str, settings: Settings,
                     min_passes: int = 1, progress=None, guides=None) -> TermEstimate:
    """dI/dθ of one term (forward mode), as the sample-weighted mean over its passes."""
    width, height = scene.resolution
    counts = term_passes(term, settings, width * height, min_passes)
    total = sum(counts)
    images, primal = [], np.zeros((height, width, 3))
    t0 = time.perf_counter()
    for p, spp in enumerate(counts):
        theta = mi.Float(0.0)
        dr.enable_grad(theta)
        parameter.apply(theta)
        img = term_image(scene, edges, view, term, spp, pass_seed(settings.seed, view, p, stream(term)), settings,
                         guides)
        dr.forward(theta)
        images.append(np.asarray(dr.grad(img), np.float64).reshape(height, width, 3))
        primal += np.asarray(dr.detach(img), np.float64).reshape(height, width, 3) * spp / total
        del img
        parameter.reset()
        if progress:
            progress(spp)
    weights = [c / total for c in counts]
    mean = sum(w * g for w, g in zip(weights, images))
    return TermEstimate(term, mean, images, weights, time.perf_counter() - t0,
                        primal if term == "interior" else None)


def ad_image(scene, edges, view: int, terms, settings: Settings, pass_index: int = 0,
             scale: float = 1.0, guides=None) -> mi.Float:
    """Sum of the requested terms for one pass (flat W·H·3, AD), for reverse mode.

    The primal value is the interior image (zero when ``interior`` is not requested)."""
    width, height = scene.resolution
    img = dr.zeros(mi.Float, width * height * 3)
    for term in terms:
        spp = term_passes(term, settings, width * height)[0]
        img = img + term_image(scene, edges, view, term, spp,
                               pass_seed(settings.seed, view, pass_index, stream(term)), settings, guides)
    return img * scale
