"""The part of an optimisation iteration that Dr.Jit records once and replays (``dr.freeze``,
issue 38): for the mini-batch of views v₁…v_B, the adjoint render P (``optimize.adjoint_spp``
samples per pixel), the L1 loss and its adjoint

    ℓ = Σ |P − T| / (3·W·H·B),    δ = sign(P − T) / (3·W·H·B),

and the interior term's reverse pass, the backward of Σ δ·I_interior into the scene's leaf
buffers (:meth:`psdr_cli.problem.Problem.apply_leaves`). This is the derivative the traced loop
takes of ``losses.l1.l1_loss`` with an adjoint render (mean over the views of mean
sign(P − T)·∂I), split by term: the loop adds the other terms' Σ δ·I_term traced, and one backward
pass through the large-steps solve carries the leaves' gradient to the optimiser.

Everything that varies between iterations enters as data: the batch as an array of view indices
into the run's cameras (:class:`.estimators.camera.CameraTable`), the seeds as arrays, the targets
of all views as one array. A recording is replayed only while the structure it was recorded on
holds (:class:`BatchShape`: the scene object, the film, the batch size, the sample counts and
passes); when it changes (a remesh builds a new scene, a stage a new film) the next call is traced
and recorded again. The terms that read numpy between their kernels (the primary term's curve
selection, the boundary terms' edge table and guides) stay traced.

Parameters (experiment keys)
----------------------------
``optimize.freeze`` (bool, default true)
    Record and replay this part when the run allows it (:func:`refusal` says when it does not);
    false: every iteration is traced as before (the same estimator; the cameras from Mitsuba's
    sensor objects instead of the table, equal up to rounding).
"""
from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from .estimators.camera import CameraTable, is_perspective, table_camera_rays
from .estimators.interior import radiance
from .estimate import term_passes
from .estimators.passes import AD_LANES, make_sampler, passes_for, views_seed
from .estimators.registry import ADJOINT_STREAM, RENDER_STREAM
from .estimators.registry import term as registry_term
from .jitarray import jit_array

#: The term whose reverse pass is recorded (the others read numpy between their kernels).
FROZEN_TERM = "interior"


@dataclass(frozen=True)
class BatchShape:
    """What a recording is valid for: the scene object (a remesh builds a new one), the film
    W × H, the batch size B, the interior term's samples per pixel, the adjoint render's passes,
    the path depth and whether camera rays that leave the scene see the background."""
    scene_id: int
    width: int
    height: int
    views: int
    spp: int
    adjoint_passes: tuple
    max_depth: int
    hide_background: bool


def refusal(problem, stage, cfg, engine, settings, batch: int) -> str | None:
    """Why the frozen part cannot serve this run (None: it can). It needs psdr's interior term
    with a batch of ``batch`` views in one AD pass, an adjoint render, the L1 loss alone (no pixel
    weights or masks), the optimiser's unknowns written into the scene as plain buffers
    (no environment rotation) and Mitsuba's perspective cameras, fixed."""
    if not getattr(cfg, "freeze", True):
        return "optimize.freeze is false"
    if engine.name != "psdr" or FROZEN_TERM not in engine.terms:
        return "the interior term is not psdr's"
    if not cfg.adjoint_spp:
        return "no adjoint render (optimize.adjoint_spp)"
    if stage.weights or stage.masks is not None:
        return "pixel weights or masks"
    if problem.envmap:
        return "an environment rotation"
    if not all(is_perspective(s) for s in problem.scene.sensors):
        return "a camera other than Mitsuba's perspective camera"
    width, height = problem.scene.resolution
    if batch * width * height * term_passes(FROZEN_TERM, settings, width * height)[0] > AD_LANES:
        return "the batch's interior pass is wider than one AD pass"
    return None


def batch_loss(shape: BatchShape, mi_scene, table: CameraTable, targets: mi.Float, views: mi.UInt32,
               interior_seed: mi.UInt32, adjoint_seeds: list):
    """(ℓ, δ) of the module docstring, the interior term's backward pass run here. ``targets``
    holds every view's target (flat W·H·3 each, view-major), ``views`` the batch's indices into it
    and into ``table``; ``adjoint_seeds`` one seed per pass of ``shape.adjoint_passes``."""
    n = 3 * shape.width * shape.height
    spp_adjoint = sum(shape.adjoint_passes)
    with dr.suspend_grad():
        P = None
        for spp, seed in zip(shape.adjoint_passes, adjoint_seeds):
            sums = pass_sums(shape, mi_scene, table, views, spp, seed, ad=False)
            P = sums if P is None else P + sums
        P = P / spp_adjoint
        lane = dr.arange(mi.UInt32, n * shape.views)
        k = lane // dr.opaque(mi.UInt32, n)
        T = dr.gather(mi.Float, targets, dr.gather(mi.UInt32, views, k) * n + (lane - k * n))
        residual = P - T
        scale = 1.0 / (n * shape.views)
        loss = dr.sum(dr.abs(residual)) * scale
        delta = dr.sign(residual) * scale
    image = pass_sums(shape, mi_scene, table, views, shape.spp, interior_seed, ad=True) / shape.spp
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
    """The recorded part of a run's iterations (module docstring). ``enabled`` false runs the same
    function traced every call (the fallback, and the reference the tests compare with)."""

    def __init__(self, enabled: bool = True):
        self.enabled = enabled
        self.shape = None
        self.fn = None
        self.table = self.targets = None
        self.recordings = 0  # recordings made by earlier shapes' functions

    def structure(self, problem, stage, views, settings, cfg) -> BatchShape:
        width, height = problem.scene.resolution
        spp = term_passes(FROZEN_TERM, settings, width * height)[0]  # one pass per iteration, as ad_images
        return BatchShape(id(problem.scene.mi_scene), width, height, len(views), spp,
                          tuple(passes_for(cfg.adjoint_spp, width * height * len(views))),
                          settings.max_depth, bool(problem.scene.config.hide_background))

    def prepare(self, shape: BatchShape, problem, stage):
        """A new function (and nothing of the old recordings) for a new structure."""
        if self.fn is not None and self.enabled:
            self.recordings += self.fn.n_recordings
        self.shape = shape
        body = _bind(shape)
        self.fn = dr.freeze(body, warn_after=1000) if self.enabled else body
        self.table = CameraTable.of(problem.scene.sensors, shape.width, shape.height)
        self.targets = jit_array(mi.Float, np.concatenate([np.ravel(np.asarray(a, np.float32))
                                                             for a in stage.arrays]))

    def __call__(self, problem, stage, views, iteration: int, settings, cfg):
        """(ℓ, δ) of iteration ``iteration``'s batch ``views`` on the current scene (whose
        unknowns are leaves: the interior term's gradient is accumulated into them)."""
        shape = self.structure(problem, stage, views, settings, cfg)
        if shape != self.shape:
            self.prepare(shape, problem, stage)
        interior = views_seed(settings.seed, views, iteration, registry_term(FROZEN_TERM).stream)
        adjoint = views_seed(settings.seed, views, iteration, ADJOINT_STREAM)
        seeds = [mi.UInt32(views_seed(adjoint, views, p, RENDER_STREAM)) for p in range(len(shape.adjoint_passes))]
        return self.fn(problem.scene.mi_scene, self.table, self.targets, mi.UInt32(views), mi.UInt32(interior), seeds)

    @property
    def n_recordings(self) -> int:
        """Recordings made so far (0 when not enabled)."""
        if not self.enabled:
            return 0
        return self.recordings + (self.fn.n_recordings if self.fn is not None else 0)


def _bind(shape: BatchShape):
    def body(mi_scene, table, targets, views, interior_seed, adjoint_seeds):
        return batch_loss(shape, mi_scene, table, targets, views, interior_seed, adjoint_seeds)
    return body
