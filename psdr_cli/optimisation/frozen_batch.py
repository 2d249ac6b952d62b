"""Owns the part of an optimisation iteration that Dr.Jit records once and replays
(``dr.freeze``). Reads the problem's scene, the cameras, the targets and the iteration's edges and
curves; writes the gradients of the scene's leaf buffers.

For the mini-batch of views v₁…v_B it records the adjoint render P (``optimize.adjoint_spp``
samples per pixel; without one, the rendering term's own primal), the loss ℓ and its adjoint
δ = ∂ℓ/∂I, summed over the losses of :mod:`.losses.registry` that apply to the run, each in its
recorded form (:class:`.losses.loss.RecordedLoss`; the L1 loss's

    ℓ = Σ |P − T| / (3·W·H·B),    δ = sign(P − T) / (3·W·H·B)   (0 where P = T without an adjoint render),

the derivative the traced loop takes of ``losses.l1.l1_loss``: Dr.Jit's derivative of |x| is 0
at x = 0), and the rendering term's reverse pass (the interior term,
:data:`.estimators.registry.RENDERING`), the backward of Σ δ·I into the scene's leaf buffers
(:meth:`psdr_cli.optimisation.problem.Problem.apply_leaves`): the traced loop's derivative of its loss, split
by term (a run with a loss that has no recorded form is traced: :func:`refusal`). Once the
iteration's edge table is there, the boundary terms with a recorded part
(:data:`.estimators.registry.RECORDED`, :class:`.estimators.recording.RecordedPart`) replay
their backward passes of Σ δ·I_term, unguided, where their part serves the iteration. The loop
adds the other terms' Σ δ·I_term traced, and one backward pass through the large-steps solve
carries the leaves' gradient to the optimiser.

Everything that varies between iterations enters as data: the batch as an array of view indices
into the run's cameras (:class:`.estimators.camera.CameraTable`), the seeds as arrays, the targets
of all views as one array, the edges and curves as padded arrays with their counts. A recording
is replayed only while the structure it was recorded on holds (:class:`BatchShape` and the
parts' own: the scene object, the film, the batch size, the sample counts and passes, the
losses, the slots); when it changes (a remesh builds a new scene, a stage a new film) the next
call is traced and recorded again. Guided passes, which read their guides' numpy between
kernels, stay traced.

Parameters (experiment keys)
----------------------------
``optimize.freeze`` (bool, default true)
    Record and replay this part when the run allows it (:func:`refusal` says when it does not);
    false: every iteration is traced (the same estimator; the cameras from Mitsuba's
    sensor objects instead of the table, equal up to rounding).
"""
from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from ..estimators import registry
from ..estimators.boundary_sampling import sensor_origins
from ..estimators.camera import CameraTable, table_camera_rays
from ..estimators.interior import radiance
from ..estimators.passes import AD_LANES, make_sampler, passes_for, views_seed
from ..estimators.recording import PassInputs, RecordedScene, Recording, opaque
from ..estimators.registry import ADJOINT_STREAM, RENDER_STREAM
from ..losses.registry import recorded_names, recorded_sum, recording_refusal
from ..rendering.estimate import has_guide, term_passes
from ..scene.sensors import is_perspective
from ..support.jitarray import jit_array


@dataclass(frozen=True)
class BatchShape:
    """What a recording is valid for: the scene object (a remesh builds a new one), the film
    W × H, the batch size B, the interior term's samples per pixel, the adjoint render's passes,
    the path depth, whether camera rays that leave the scene see the background, and the names of
    the losses that apply to the run, whose recorded forms it sums."""
    scene_id: int
    width: int
    height: int
    views: int
    spp: int
    adjoint_passes: tuple
    max_depth: int
    hide_background: bool
    losses: tuple


def refusal(problem, stage, cfg, engine, settings, batch: int) -> str | None:
    """Why the frozen part cannot serve this run (None: it can). It needs psdr's interior term
    with a batch of ``batch`` views in one AD pass, for every loss that applies to the run a
    recorded form that stands for it on ``stage`` (:func:`.losses.registry.recording_refusal`: the
    L1 loss's takes no pixel weights, the silhouette loss of masked views has none), the shape as
    the only unknown (its vertex buffer written by the large-steps solve: Dr.Jit 1.5 replays a
    buffer written from the host wrongly, docs/benchmarks/iteration_time.md, "The recorded part of
    an iteration") and Mitsuba's perspective cameras, fixed."""
    if not cfg.freeze:
        return "optimize.freeze is false"
    if engine.name != "psdr" or registry.RENDERING not in engine.terms:
        return "the rendering term is not psdr's"
    losses = recording_refusal(stage, cfg)
    if losses is not None:
        return losses
    if list(problem.opt.keys()) != ["u"] or any(u.name not in ("shape", "cameras") for u in problem.unknowns):
        return "unknowns besides the shape (albedo, lighting, materials)"
    if problem.cameras is not None and (problem.cameras.attached or problem.cameras.moved):
        return "camera poses refined (the recorded batch holds the starting cameras as constants)"
    if not all(is_perspective(s) for s in problem.scene.sensors):
        return "a camera other than Mitsuba's perspective camera"
    width, height = problem.scene.resolution
    if batch * width * height * term_passes(registry.RENDERING, settings, width * height)[0] > AD_LANES:
        return "the batch's interior pass is wider than one AD pass"
    return None


def batch_loss(shape: BatchShape, mi_scene, table: CameraTable, targets: mi.Float, views: mi.UInt32,
               interior_seed: mi.UInt32, adjoint_seeds: list):
    """(ℓ, δ) of the module docstring, the interior term's backward pass run here. ``targets``
    holds every view's target (flat W·H·3 each, view-major), ``views`` the batch's indices into it
    and into ``table``; ``adjoint_seeds`` one seed per pass of ``shape.adjoint_passes``. Without
    adjoint passes P is the interior render's own primal (the losses' derivatives are then those
    the traced loss takes of I itself, :class:`.losses.loss.RecordedLoss`)."""
    n = 3 * shape.width * shape.height
    image = pass_sums(shape, mi_scene, table, views, shape.spp, interior_seed, ad=True) / shape.spp
    with dr.suspend_grad():
        if shape.adjoint_passes:
            P = None
            for spp, seed in zip(shape.adjoint_passes, adjoint_seeds):
                sums = pass_sums(shape, mi_scene, table, views, spp, seed, ad=False)
                P = sums if P is None else P + sums
            P = P / sum(shape.adjoint_passes)
        else:
            P = dr.detach(image)
        lane = dr.arange(mi.UInt32, n * shape.views)
        k = lane // n  # (literals here and below: recorded per structure; an opaque scalar is a memset per replay)
        T = dr.gather(mi.Float, targets, dr.gather(mi.UInt32, views, k) * n + (lane - k * n))
        loss, delta = recorded_sum(shape.losses, P, T, primal=not shape.adjoint_passes)
    dr.backward(dr.sum(delta * image))
    return loss, delta


def pass_sums(shape: BatchShape, mi_scene, table: CameraTable, views: mi.UInt32, spp: int, seed: mi.UInt32,
              ad: bool) -> mi.Float:
    """One pass of the batch's views in one wavefront: the sum over ``spp`` samples of every pixel,
    flat (B · H · W · 3), view-major (the samples of :func:`.estimators.interior.views_pass` and
    of the interior term's ``estimate_views`` with the cameras as data)."""
    sampler = make_sampler(seed, shape.width * shape.height * spp * shape.views)
    ray = table_camera_rays(table, views, sampler, spp)
    L = radiance(mi_scene, sampler, ray, shape.max_depth, ad=ad, hide_background=shape.hide_background)
    dr.eval(L)  # one kernel for the three channels
    return dr.ravel(mi.Color3f([dr.block_sum(L[c], spp, mode="evaluated") for c in range(3)]))


class FrozenBatch:
    """The recorded parts of a run's iterations (module docstring). ``enabled`` false runs the same
    functions traced every call (the fallback, and the reference the tests compare with)."""

    def __init__(self, enabled: bool = True):
        self.enabled = enabled
        self.interior = Recording(batch_loss, enabled)
        #: {term name: its recorded part} (:data:`.estimators.registry.RECORDED_PARTS`)
        self.parts = {name: part(enabled) for name, part in registry.RECORDED_PARTS.items()}
        self.scene_id = self.stage = self.scene = None
        self.recorded = self.targets = None

    def structure(self, problem, stage, views, settings, cfg) -> BatchShape:
        width, height = problem.scene.resolution
        spp = term_passes(registry.RENDERING, settings, width * height)[0]  # one pass per iteration, as ad_images
        adjoint = tuple(passes_for(cfg.adjoint_spp, width * height * len(views))) if cfg.adjoint_spp else ()
        return BatchShape(id(problem.scene.mi_scene), width, height, len(views), spp, adjoint,
                          settings.max_depth, bool(problem.scene.config.hide_background),
                          recorded_names(stage, cfg))

    def prepare(self, problem, stage):
        """The cameras and the targets of a new scene or stage as arrays."""
        width, height = problem.scene.resolution
        self.scene_id, self.stage = id(problem.scene.mi_scene), stage
        self.scene = problem.scene.mi_scene  # held: its id cannot name another scene meanwhile
        self.recorded = RecordedScene(self.scene_id, CameraTable.of(problem.scene.sensors, width, height),
                                      sensor_origins(problem.scene.sensors))
        for part in (self.interior, *self.parts.values()):
            part.reset()  # (a recording keyed by a scene's id must not outlive it: ids are reused)
        self.targets = jit_array(mi.Float, np.concatenate([np.ravel(np.asarray(a, np.float32))
                                                             for a in stage.arrays]))

    def __call__(self, problem, stage, views, iteration: int, settings, cfg):
        """(ℓ, δ) of iteration ``iteration``'s batch ``views`` on the current scene (whose
        unknowns are leaves: the rendering term's gradient is accumulated into them)."""
        shape = self.structure(problem, stage, views, settings, cfg)
        if shape.scene_id != self.scene_id or stage is not self.stage:
            self.prepare(problem, stage)
        interior = views_seed(settings.seed, views, iteration, registry.term(registry.RENDERING).stream)
        adjoint = views_seed(settings.seed, views, iteration, ADJOINT_STREAM)
        seeds = [opaque(views_seed(adjoint, views, p, RENDER_STREAM)) for p in range(len(shape.adjoint_passes))]
        return self.interior(shape, problem.scene.mi_scene, self.recorded.table, self.targets, mi.UInt32(views),
                             opaque(interior), seeds)

    def serves(self, term: str, problem, views, settings, edges, guides) -> bool:
        """Whether ``term``'s recorded part can run on this iteration's ``edges`` (it has one, its
        passes are unguided, and the part serves them)."""
        if term not in self.parts or has_guide(guides, term):
            return False
        width, height = problem.scene.resolution
        return self.parts[term].serves(problem.scene, views, term_passes(term, settings, width * height)[0], edges)

    def record(self, term: str, problem, views, iteration: int, settings, *, edges, delta: mi.Float) -> int:
        """``term``'s backward pass of Σ δ·I_term over the batch ``views`` (into the scene's
        leaves), replayed; :meth:`__call__` must have run for this scene. Returns the part's count
        of edges or curves."""
        if id(problem.scene.mi_scene) != self.scene_id:
            raise RuntimeError(f"FrozenBatch.record({term!r}): the batch's part must run first for this scene")
        width, height = problem.scene.resolution
        inputs = PassInputs(views, views_seed(settings.seed, views, iteration, registry.term(term).stream),
                            term_passes(term, settings, width * height)[0], settings.estimator, settings.max_depth)
        return self.parts[term].run(self.recorded, inputs, problem.scene, edges=edges, delta=delta)

    def boundary(self, problem, views, iteration: int, settings, *, edges, guides, delta: mi.Float, terms) -> tuple:
        """The recorded backward passes of the ``terms`` whose part serves this iteration, in
        :data:`.estimators.registry.RECORDED` order; returns the terms left to trace."""
        for term in self.parts:
            if term in terms and self.serves(term, problem, views, settings, edges, guides):
                self.record(term, problem, views, iteration, settings, edges=edges, delta=delta)
                terms = tuple(t for t in terms if t != term)
        return terms

    @property
    def n_recordings(self) -> int:
        """Recordings made so far (0 when not enabled)."""
        return self.interior.n_recordings + sum(part.n_recordings for part in self.parts.values())
