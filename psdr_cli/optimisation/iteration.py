"""One iteration of an optimisation: its mini-batch rendered with AD, the L1 loss and its
adjoint (and, for masked photographs, the silhouette loss: :mod:`psdr_cli.losses`), the guides
refreshed on their schedule, and one Adam step at the iteration's learning rate (skipped on a
non-finite gradient)."""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from functools import partial

import drjit as dr
import mitsuba as mi
import numpy as np

from ..estimators import registry
from ..estimators.boundary_sampling import edge_list
from ..estimators.interior import split_views
from ..estimators.passes import pass_seed, views_seed
from ..estimators.registry import ADJOINT_STREAM
from ..estimators.sample_log import SampleLog
from ..guiding.loop_fed import fed_term, fitted_guides, guide_arrays, log_from_arrays, per_pass_budget
from ..guiding.targets import Guides
from ..losses.loss import ViewImages
from ..losses.registry import view_losses
from ..rendering.estimate import make_guides
from ..rendering.render import render_view, render_views
from ..support.jitarray import jit_array
from .frozen_batch import FrozenBatch, refusal
from .geometry_ahead import GeometryAhead
from .unknowns.unknown import At, Saved


@dataclass
class Loop:
    """What every iteration of a run uses: the ``optimize`` section, the engine that renders each
    view (its settings hold the estimator, the terms and the seed: the one source of each), the
    run's length (the learning-rate schedule's), where one-line warnings go and the factor
    gradient spikes are clipped to (:mod:`psdr_cli.optimisation.outlier_clip`)."""
    cfg: object
    engine: object
    total: int
    warn: object
    clip: float | None = None  # the gradient clip factor (outlier_clip.clip_factor), None: no clipping
    frozen: FrozenBatch | None = None  # the recorded part of the iterations (frozen_batch.py), None: all traced

    @property
    def settings(self):
        return self.engine.settings

    @property
    def terms(self) -> tuple:
        return self.engine.terms


@dataclass
class Step:
    """What one iteration measured: its loss, whether its update was skipped, and the times
    (``time.perf_counter``) at which guiding, rendering and the update began and it ended
    (``t_render == t_guide`` when the iteration built no guide)."""
    loss: float
    skipped: bool
    t_guide: float
    t_render: float
    t_post: float
    t_end: float


class GuideCache:
    """The guides in use and the shape and unknowns they were built from (saved with the state,
    so that a resumed run rebuilds the same guides). A term whose guides the loop feeds (its
    ``GuideTarget.loop_fed`` and a loop-fed guide kind: :mod:`psdr_cli.guiding.loop_fed`) keeps
    them in ``log`` with the samples its passes kept since the last fit."""

    def __init__(self, guides=None, snapshot=None, log=None):
        self.guides, self.snapshot, self.log = guides, snapshot, log

    @classmethod
    def resumed(cls, problem, loop: Loop, state, stage) -> "GuideCache":
        """The guides in use when the run stopped: built ones rebuilt from the shape they were
        built from, loop-fed ones and their samples as saved (none for a fresh run, or a stage
        that is not guided)."""
        if not stage.guided or (state.guide_V is None and not state.guide_arrays):
            return cls()
        fed, built = split_terms(loop.settings, loop.terms)
        guides = Guides()
        if state.guide_V is not None and built:
            guides = rebuild_guides(problem, loop.settings, Saved(state.guide_V, state.guide_values),
                                    len(stage.arrays), built)
        log = None
        if fed:
            log = log_from_arrays(state.guide_arrays, window_budget(loop.cfg, len(stage.arrays)))
            guides[fed] = log
        snapshot = (state.guide_V, state.guide_values) if state.guide_V is not None else None
        return cls(guides, snapshot, log)

    def reset(self):
        """No guides and no kept samples (a remesh changed the edges they index)."""
        self.guides = self.snapshot = self.log = None

    def refresh(self, problem, edges, stage, loop: Loop):
        """Build the built guides anew (for every view of ``stage``), fit the loop-fed term's
        guides to the samples kept since the last refresh (none yet: the term runs unguided and
        keeps samples)."""
        views, settings, cfg = len(stage.arrays), loop.settings, loop.cfg
        fed, built = split_terms(settings, loop.terms)
        with dr.suspend_grad():
            guides = make_guides(problem.scene, edges, list(range(views)), built, settings)
            if fed:
                fitted = {}
                if self.log is not None and self.log.kept and edges.count > 0:
                    P = dr.detach(edges.positions(mi.traverse(problem.scene.mi_scene)))
                    fitted = fitted_guides(self.log, edges.breakpoints(P), settings.estimator)
                self.log = guides[fed] = SampleLog(fitted, window_budget(cfg, views))
        self.guides = guides
        self.snapshot = (problem.vertices(), problem.values())

    def arrays(self) -> dict:
        """The loop-fed guides and their kept samples as flat arrays (empty without them)."""
        return guide_arrays(self.log) if self.log is not None else {}

    def memory_bytes(self) -> int:
        return sum(g.stats.memory_bytes for _, g in self.guides.all()) if self.guides else 0


def split_terms(settings, terms) -> tuple:
    """(the term whose guides the loop feeds, or None; the guided terms whose guides are built),
    from the guide kinds ``settings`` decided (:func:`psdr_cli.guiding.loop_fed.fed_term`)."""
    kinds = settings.guide_kinds(terms)
    fed = fed_term(kinds)
    return fed, [t for t, kind in kinds.items() if kind != "none" and t != fed]


def window_budget(cfg, views: int) -> int:
    """Samples a pass keeps for the loop-fed guides (a window: ``guide_every`` iterations of
    ``batch_size`` passes, at most one per view)."""
    return per_pass_budget(cfg.guide_every * min(cfg.batch_size, views))


@dataclass
class Batch:
    """An iteration's mini-batch: its ``views``, the iteration number ``it`` and its edge table:
    ``edges`` once fetched, fetched from ``ahead`` (the worker thread that builds it; None when
    the engine needs no edges) when first needed (:meth:`edge_table`)."""
    views: list
    it: int
    ahead: GeometryAhead | None
    edges: object = None

    def edge_table(self):
        """The edge table (waits for the worker the first time), or None without one."""
        if self.edges is None and self.ahead is not None:
            self.edges = self.ahead.edges()
        return self.edges


def iterate(problem, loop: Loop, stage, guides: GuideCache, it: int) -> Step:
    """Iteration ``it`` of the run ``loop`` on the shape of ``problem``."""
    cfg, engine, settings, warn = loop.cfg, loop.engine, loop.settings, loop.warn
    n_views, seed = len(stage.arrays), settings.seed
    views = batch_views(seed, it, n_views, cfg.batch_size)
    problem.begin(it, loop.total)  # optimize.cameras: the poses move from their start on
    frozen = loop.frozen is not None and refusal(problem, stage, cfg, engine, settings, len(views)) is None
    problem.write_as_leaves(frozen)  # the form the loop's apply after the step writes (problem.py)
    if frozen:
        values, leaves = problem.apply_leaves()
    else:
        problem.apply()  # (the scene's copy of the mesh too, for the edge table)
    intersections = any(registry.term(t).reads_intersections for t in engine.terms)
    ahead = GeometryAhead(problem.scene, settings.estimator, settings.edge_sort, intersections) \
        if engine.needs_edges else None  # the edge table on the worker thread (geometry_ahead.py)
    batch = Batch(views, it, ahead)
    t_guide = time.perf_counter()
    anchor = max([a for a in cfg.remesh.at if a <= it] + [0])  # guides restart after a remesh
    build = stage.guided and (guides.guides is None or (it - anchor) % cfg.guide_every == 0)
    if build:
        guides.refresh(problem, batch.edge_table(), stage, loop)
    t_render = time.perf_counter() if build else t_guide  # no guide built: no guiding time
    if frozen:
        loss = frozen_loss(problem, loop, stage, guides, batch)
        if dr.grad_enabled(loss):
            dr.backward(loss)
        problem.backward_leaves(values, leaves)
    else:
        loss = traced_loss(problem, loop, stage, guides, batch)
        dr.backward(loss)
    problem.invalidate()  # the backward pass used up the scene's AD graph: the next apply rebuilds it
    loss_value = float(loss[0])
    t_post = time.perf_counter()
    skipped = not problem.finite_gradients() or not math.isfinite(loss_value)
    if skipped:
        warn(f"iteration {it}: non-finite gradient or loss; update skipped")
        problem.drop_gradients()
    else:  # Adam at the iteration's rate, then each unknown's own step (ranges, the cameras' Adam)
        rate = learning_rate_at(cfg, it, loop.total) if cfg.learning_rate_final is not None else None
        problem.step(At(it, loop.total, warn), rate, loop.clip)
    return Step(loss_value, skipped, t_guide, t_render, t_post, time.perf_counter())


def traced_loss(problem, loop: Loop, stage, guides: GuideCache, batch: Batch) -> mi.Float:
    """The iteration's loss: every view's losses (:mod:`psdr_cli.losses`) over the batch, the
    unknowns' priors added, its AD graph reaching the optimiser's variables."""
    cfg, engine = loop.cfg, loop.engine
    views, it = batch.views, batch.it
    loss = mi.Float(0.0)
    # the adjoint render first: its kernels run while the worker builds the edge table
    adjoints = adjoint_images(problem.scene, views, cfg.adjoint_spp, loop.settings.seed, it) if cfg.adjoint_spp \
        else [None] * len(views)
    edges = batch.edge_table()
    images = engine.images(problem, edges, views, it, guides.guides)
    for v, img, adjoint in zip(views, images, adjoints):
        view = ViewImages(img, stage.arrays[v], adjoint, stage.weights[v] if stage.weights else None,
                          stage.masks[v] if stage.masks is not None else None,
                          partial(engine.coverage, problem, edges, v, it))
        for value in view_losses(view, cfg):  # losses/registry.py
            loss += value / len(views)
    prior = problem.prior()  # the unknowns' priors (optimize.envmap.smoothness)
    if prior is not None:
        loss += prior
    return loss


def frozen_loss(problem, loop: Loop, stage, guides: GuideCache, batch: Batch) -> mi.Float:
    """The iteration's loss with the recorded parts (:mod:`psdr_cli.optimisation.frozen_batch`: the recorded
    forms of the losses that apply): the adjoint render (if any), the loss and its adjoint δ and
    the rendering term's backward pass replayed, then the boundary terms whose recorded part
    serves the iteration (their gradient already in the scene's leaves), the other terms traced
    as Σ_v Σ δ_v·I_v,term, whose primal value is 0, and the priors.
    Returns ℓ + that sum + the priors, for one backward pass of the traced part."""
    engine = loop.engine
    views, it = batch.views, batch.it
    loss, delta = loop.frozen(problem, stage, views, it, loop.settings, loop.cfg)
    edges = batch.edge_table()
    rest = tuple(t for t in engine.terms if t != registry.RENDERING)
    rest = loop.frozen.boundary(problem, views, it, loop.settings, edges=edges, guides=guides.guides, delta=delta,
                                terms=rest)
    if rest:
        images = engine.images(problem, edges, views, it, guides.guides, terms=rest)
        for d, img in zip(split_views(delta, len(views)), images):
            loss = loss + dr.sum(d * img)
    prior = problem.prior()
    if prior is not None:
        loss = loss + prior
    return loss


def batch_views(seed: int, iteration: int, count: int, size: int) -> list:
    """The mini-batch of iteration ``iteration``: a function of (seed, iteration) only."""
    rng = np.random.default_rng([seed, iteration])
    return sorted(rng.choice(count, size=min(size, count), replace=False).tolist())


def learning_rate_at(cfg, iteration: int, total: int) -> float:
    """Adam's step at ``iteration`` of a ``total``-iteration run: ``learning_rate`` up to the last
    remesh s (the last of ``remesh.at`` before ``total``, else 0), then the geometric decay
    lr(i) = lr · (lr_final / lr)^((i − s) / (total − 1 − s)), reaching ``learning_rate_final``
    at the last iteration; constant when ``learning_rate_final`` is unset."""
    lr, final = cfg.learning_rate, cfg.learning_rate_final
    s = max([a for a in cfg.remesh.at if a < total] + [0])
    if final is None or iteration <= s or total - 1 <= s:
        return lr
    return lr * (final / lr) ** (min(iteration - s, total - 1 - s) / (total - 1 - s))


def rebuild_guides(problem, settings, saved: Saved, n_views: int, terms):
    """The guides of ``problem`` as they were built from the saved shape and unknowns ``saved``
    (a resumed run continues with the guides the interrupted run was using; guide building is
    seeded, so they are the same guides). The scene is left for :meth:`Problem.apply` to reset."""
    problem.write_saved(saved)
    with dr.suspend_grad():
        edges = edge_list(problem.scene, settings.estimator, settings.edge_sort)
        return make_guides(problem.scene, edges, list(range(n_views)), terms, settings)


def adjoint_images(scene, views, spp: int, seed: int, iteration: int) -> list:
    """:func:`adjoint_image` of each of ``views``: several traced as one wavefront per pass
    (:func:`psdr_cli.rendering.render.render_views`, from their own random stream); one view alone
    through :func:`adjoint_image`."""
    if len(views) == 1:
        return [adjoint_image(scene, views[0], spp, seed, iteration)]
    return render_views(scene, views, spp, seed=views_seed(seed, views, iteration, ADJOINT_STREAM))


def adjoint_image(scene, view: int, spp: int, seed: int, iteration: int) -> mi.Float:
    """Primal render P of ``view`` (flat W·H·3, no AD) from samples of its own random stream, for
    the derivative of :func:`psdr_cli.losses.l1.l1_loss`."""
    image = render_view(scene, view, spp, seed=pass_seed(seed, view, iteration, ADJOINT_STREAM))
    return jit_array(mi.Float, np.ravel(image))
