"""The estimate of dI/dθ, the library behind ``psdr grad``, ``psdr compare`` and the
optimisation loop: every term of dI/dθ = interior + primary + direct + indirect, in passes.

``term_image`` computes one pass of a term by its :class:`~psdr_cli.estimators.term.Term`
(looked up in :mod:`psdr_cli.estimators.registry`): a flat W·H·3 AD image whose primal value is
the rendered image for the interior term and 0 for the boundary terms (they only carry
derivatives). The same images serve forward mode (θ → gradient image, :func:`forward_gradient`)
and reverse mode (image loss → scene parameters, :func:`ad_image` + ``dr.backward``).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import drjit as dr
import mitsuba as mi
import numpy as np

from ..config.estimator_section import EstimatorConfig
from ..config.experiment_file import Experiment
from ..config.options import parse_terms, with_estimator
from ..errors import PsdrError
from ..estimators import registry
from ..estimators.boundary_sampling import BoundaryEdges, edge_list
from ..estimators.passes import AD_LANES, pass_seed, passes_for, views_seed
from ..geometry.parameters import Parameter
from ..guiding import auto
from ..guiding.targets import Guides, build_guides
from ..scene.build import build_scene
from .camera_motion import check_camera_motion, with_all_edges



@dataclass
class Settings:
    """What one gradient estimate uses: the experiment's validated estimator configuration
    (sample counts, techniques, guide parameters; per-call overrides are copies of it), the
    scene's path depth, the seed, and the guide of each boundary term (``kinds``), decided here
    once from ``estimator.guiding``, the image's ``pixels`` and whether the settings are the
    optimisation ``loop``'s (:func:`psdr_cli.guiding.auto.decide`; a copy with other estimator
    keys decides again)."""
    estimator: EstimatorConfig = field(default_factory=EstimatorConfig)
    max_depth: int = 3
    seed: int = 0
    pixels: int = 0
    loop: bool = False
    kinds: dict = field(init=False, repr=False, compare=False)

    def __post_init__(self):
        self.kinds = auto.decide(self.estimator.guiding, self.pixels, self.estimator.boundary_spp, self.loop)

    @staticmethod
    def from_experiment(exp: Experiment, spp: int | None = None, seed: int | None = None,
                        loop: bool = False) -> "Settings":
        """The settings of ``exp``'s images (``loop``: of its optimisation loop)."""
        est = replace(exp.estimator, spp=spp) if spp else exp.estimator
        return Settings(est, exp.scene.max_depth, exp.seed if seed is None else seed,
                        exp.scene.width * exp.scene.height, loop)

    def guide_kinds(self, terms) -> dict:
        """{term: guide kind} of the guidable terms among ``terms`` (``none``: unguided)."""
        return {t: k for t, k in self.kinds.items() if t in terms}

    def with_estimator(self, **changes) -> "Settings":
        """A copy whose estimator keys (spp, guiding, passes, ...) are replaced."""
        return replace(self, estimator=replace(self.estimator, **changes))

    @property
    def spp(self) -> int:
        return self.estimator.spp

    @property
    def primary_spp(self) -> int:
        return self.estimator.primary_spp

    @property
    def boundary_spp(self) -> int:
        return self.estimator.boundary_spp

    @property
    def passes(self) -> int:
        return self.estimator.passes

    @property
    def sampling(self) -> str:
        return self.estimator.sampling

    @property
    def guiding(self) -> str:
        return self.estimator.guiding

    @property
    def edge_sort(self) -> bool:
        return self.estimator.edge_sort

    def samples(self, term: str) -> int:
        """Samples per pixel of ``term``."""
        return getattr(self.estimator, registry.term(term).samples_key)

    def with_samples(self, term: str, spp: int) -> "Settings":
        """A copy in which ``term`` has ``spp`` samples per pixel."""
        return self.with_estimator(**{registry.term(term).samples_key: spp})


@dataclass
class GradientSetup:
    """Everything a gradient of an experiment needs: its scene, θ, boundary edges and settings."""
    scene: object
    parameter: Parameter
    edges: BoundaryEdges
    settings: Settings

    def __iter__(self):  # scene, parameter, edges, settings = prepare(exp)
        return iter((self.scene, self.parameter, self.edges, self.settings))


def prepare(exp: Experiment, spp: int | None = None, scene=None) -> GradientSetup:
    """(scene, θ, boundary edges, settings) of a loaded experiment (its Mitsuba variant active);
    ``spp`` (the interior term's samples per pixel) as its command checked it."""
    if exp.parameter is None:
        raise PsdrError(f"{exp.file}: parameter: missing (expected e.g. {{object: NAME, kind: translate, axis: [1, 0, 0]}})")
    settings = Settings.from_experiment(exp, spp)
    scene = scene or build_scene(exp)
    if exp.parameter.camera is not None:  # every surface's discontinuities move in the image
        with_all_edges(scene)
        check_camera_motion(scene, exp.parameter.camera)
    edges = edge_list(scene, exp.estimator, settings.edge_sort)
    return GradientSetup(scene, Parameter(scene, exp.parameter), edges, settings)


def term_passes(term: str, settings: Settings, pixels: int, min_passes: int = 1) -> list[int]:
    """Samples per pixel of each pass of ``term``: at least ``max(passes, min_passes)`` passes,
    each of at most ``AD_LANES`` lanes."""
    return passes_for(settings.samples(term), pixels, AD_LANES, max(settings.estimator.passes, min_passes))


def make_guides(scene, edges: BoundaryEdges, views, terms, settings: Settings, parameter=None) -> Guides:
    """Guides of the guided terms among ``terms`` for ``views``, of the kinds ``settings``
    decided (empty when none is guided; ``guiding: auto`` picks per term,
    :mod:`psdr_cli.guiding.auto`). With the scalar ``parameter`` θ (forward mode) the direct
    term's guides follow dv/dθ, velocity included."""
    return build_guides(scene, edges, list(views), settings.guide_kinds(terms), settings.sampling,
                        settings.max_depth, settings.estimator, seed=settings.seed, parameter=parameter)


def uses_guides(settings: Settings, terms) -> bool:
    """Whether any of ``terms`` is guided under ``settings``."""
    return any(k != "none" for k in settings.guide_kinds(terms).values())


def guiding_line(settings: Settings, terms=None) -> str:
    """One line saying what guides the boundary terms get under ``settings`` (``auto`` as
    decided; in the optimisation loop when they are the loop's)."""
    kinds = settings.guide_kinds(parse_terms(terms) or settings.estimator.terms)
    return auto.describe(settings.guiding, kinds, settings.pixels * settings.boundary_spp, settings.loop)


def has_guide(guides, term: str) -> bool:
    """Whether ``guides`` hold a guide of ``term``. A loop-fed term's sample log counts even
    before its first fit: empty (no fitted guide yet) its passes draw uniformly and keep their
    samples for the fit, so they must run as guided passes (view by view), not batched."""
    return guides is not None and guides.get(term) is not None


def term_image(scene, edges: BoundaryEdges, view: int, term: str, spp: int, seed: int,
               settings: Settings, *, guides=None):
    """One pass of ``term`` for camera ``view`` with ``spp`` samples per pixel (flat W·H·3, AD).

    ``scene`` is a :class:`psdr_cli.scene.build.Scene`; its AD state (θ or vertex gradients) must be
    set before the call. ``guides`` (:class:`psdr_cli.guiding.targets.Guides`) hold the guides
    of the guided terms."""
    guide = guides.get(term) if guides else None
    return registry.term(term).estimate(scene, edges, view, spp, seed, settings.estimator, settings.max_depth,
                                        guide=guide)


def term_seed(settings: Settings, view: int, pass_index: int, term: str) -> int:
    """Sampler seed of pass ``pass_index`` of ``term`` for camera ``view`` (the term's own stream)."""
    return pass_seed(settings.seed, view, pass_index, registry.term(term).stream)


@dataclass
class TermEstimate:
    """Forward-mode result of one term: mean gradient image and the per-pass images."""
    term: str
    gradient: np.ndarray
    passes: list = field(default_factory=list)
    weights: list = field(default_factory=list)
    seconds: float = 0.0
    primal: np.ndarray | None = None


def forward_gradient(scene, edges, parameter, view: int, term: str, settings: Settings,
                     min_passes: int = 1, *, progress=None, guides=None) -> TermEstimate:
    """dI/dθ of one term (forward mode), as the sample-weighted mean over its passes.

    Passes of equal samples per pixel that fit in one AD pass together are traced as one
    wavefront (:func:`pass_groups`): a term that traces several views at once
    (``Term.estimate_views``, unguided) is given the view once per pass, so that each pass is its
    own independent estimate from its own lanes of one sampler (seeded by :func:`views_seed` of the
    group's first pass) with one trace, one set of kernels and one forward sweep for the group. A
    group of one pass is the pass as traced alone (its seed :func:`term_seed`); a guided term's
    passes and those of a θ that moves the camera run one by one."""
    width, height = scene.resolution
    counts = term_passes(term, settings, width * height, min_passes)
    total = sum(counts)
    # grouped passes gather each lane's camera as constants (estimators/camera.py, LaneCameras):
    # passes of a moving camera run one by one, as do a guided term's
    batched = None if has_guide(guides, term) or parameter.moves_camera else registry.term(term).estimate_views
    images, primal = [], np.zeros((height, width, 3))
    t0 = time.perf_counter()
    for group in pass_groups(counts, width * height, batched is not None):
        spp = counts[group[0]]
        theta = mi.Float(0.0)
        dr.enable_grad(theta)
        parameter.apply(theta)
        if len(group) == 1:
            parts = [term_image(scene, edges, view, term, spp, term_seed(settings, view, group[0], term), settings,
                                guides=guides)]
        else:
            seed = views_seed(settings.seed, [view] * len(group), group[0], registry.term(term).stream)
            parts = batched(scene, edges, [view] * len(group), spp, seed, settings.estimator, settings.max_depth)
        dr.forward(theta)
        grads, values = [dr.grad(img) for img in parts], [dr.detach(img) for img in parts]
        dr.eval(grads, values)  # one kernel for the group's images
        for grad, value in zip(grads, values):
            images.append(np.asarray(grad, np.float64).reshape(height, width, 3))
            primal += np.asarray(value, np.float64).reshape(height, width, 3) * spp / total
        del parts, grads, values
        parameter.reset()
        if progress:
            progress(spp * len(group))
    weights = [c / total for c in counts]
    mean = sum(w * g for w, g in zip(weights, images))
    return TermEstimate(term, mean, images, weights, time.perf_counter() - t0,
                        primal if registry.term(term).renders else None)


def pass_groups(counts, pixels: int, batched: bool) -> list:
    """The passes (indices into ``counts``, their samples per pixel) traced together: runs of
    consecutive passes with equal samples per pixel whose lanes (passes · ``pixels`` · spp) fit in
    ``AD_LANES``; one pass per group when the term cannot trace several views at once."""
    groups = []
    for p, spp in enumerate(counts):
        last = groups[-1] if groups else None
        if batched and last and counts[last[0]] == spp and (len(last) + 1) * pixels * spp <= AD_LANES:
            last.append(p)
        else:
            groups.append([p])
    return groups


def ad_image(scene, edges, view: int, terms, settings: Settings, pass_index: int = 0, *,
             scale: float = 1.0, guides=None) -> mi.Float:
    """Sum of the requested terms for one pass (flat W·H·3, AD), for reverse mode.

    The primal value is the interior image (zero when ``interior`` is not requested)."""
    width, height = scene.resolution
    img = dr.zeros(mi.Float, width * height * 3)
    for term in terms:
        spp = term_passes(term, settings, width * height)[0]
        img = img + term_image(scene, edges, view, term, spp, term_seed(settings, view, pass_index, term), settings,
                               guides=guides)
    return img * scale


def ad_images(scene, edges, views, terms, settings: Settings, pass_index: int = 0, *, guides=None,
              one_by_one: bool = False) -> list:
    """:func:`ad_image` of each of ``views`` (one pass each, reverse mode). A term that can trace
    several views as one wavefront (``Term.estimate_views``, unguided) does so when their lanes fit
    in one AD pass (views · W · H · spp ≤ ``AD_LANES``), seeded by :func:`views_seed`; the other
    terms run view by view with the seeds of :func:`ad_image`. The terms are added in the order
    of ``terms`` for every view, as :func:`ad_image` adds them. ``one_by_one``: every term view
    by view (the cameras carry derivatives, which a wavefront's constant cameras would drop)."""
    width, height = scene.resolution
    images = [dr.zeros(mi.Float, width * height * 3) for _ in views]
    for term in terms:
        spp = term_passes(term, settings, width * height)[0]
        batched = registry.term(term).estimate_views
        if batched and not one_by_one and len(views) > 1 and len(views) * width * height * spp <= AD_LANES and \
                not has_guide(guides, term):
            seed = views_seed(settings.seed, views, pass_index, registry.term(term).stream)
            parts = batched(scene, edges, views, spp, seed, settings.estimator, settings.max_depth)
        else:
            parts = [term_image(scene, edges, v, term, spp, term_seed(settings, v, pass_index, term), settings,
                                guides=guides) for v in views]
        images = [image + part for image, part in zip(images, parts)]
    return images


# --------------------------------------------------------------------------------------------
# psdr grad
# --------------------------------------------------------------------------------------------
def gradient_images(exp: Experiment, view: int = 0, terms=None, spp: int | None = None, min_passes: int = 1,
                    scene=None, progress=None) -> dict:
    """Forward-mode gradient images dI/dθ of one view, without writing anything.

    Returns ``{term: TermEstimate}`` for the requested terms (default: ``estimator.terms``);
    each estimate holds the mean image (H, W, 3), the per-pass images and the seconds spent.
    ``spp`` is checked as the ``--spp`` option is (:func:`psdr_cli.config.with_estimator`)."""
    scene, parameter, edges, settings = prepare(with_estimator(exp, spp=spp), scene=scene)
    terms = parse_terms(terms) or exp.estimator.terms
    guides = make_guides(scene, edges, [view], terms, settings, parameter)
    return {t: forward_gradient(scene, edges, parameter, view, t, settings, min_passes, progress=progress,
                             guides=guides)
            for t in terms}
