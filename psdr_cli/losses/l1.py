"""Owns the photometric loss: the mean absolute difference of a render and its target, traced and
recorded. Reads a view's images; touches nothing else."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from .loss import Loss, RecordedLoss, ViewImages


def l1_loss(image: mi.Float, target: mi.Float, adjoint: mi.Float | None = None,
            weight: mi.Float | None = None) -> mi.Float:
    """L = mean |I − T| with derivative ∂L = mean sign(I − T)·∂I (with ``weight`` w:
    mean w·|I − T|, pixels of weight 0 left out). With ``adjoint`` P, an independent primal render
    of the same view, L = mean |P − T| and ∂L = mean sign(P − T)·∂I: close to the gradient of the
    noise-free image's L1 loss, where the sign from I itself gives that of E|I − T|
    (docs/optimize.md, "Gradient quality per second")."""
    w = 1.0 if weight is None else weight
    if adjoint is None:
        return dr.mean(w * dr.abs(image - target))
    sign = dr.sign(adjoint - target)
    return dr.mean(w * dr.abs(adjoint - target)) + dr.mean(w * sign * (image - dr.detach(image)))


def view_l1(view: ViewImages, optimize) -> mi.Float:
    """:func:`l1_loss` of a view of the mini-batch (its adjoint render and weights, if any)."""
    return l1_loss(view.image, view.target, view.adjoint, view.weight)


def recorded_l1(P: mi.Float, T: mi.Float, primal: bool) -> tuple:
    """(ℓ, δ) = (Σ |P − T| / N, sign(P − T) / N) over the N values of the batch (N = 3·W·H·B:
    the mean over the views of :func:`l1_loss`), with δ = 0 where P = T when P is the AD render's
    own ``primal`` (the derivative of |I − T| that Dr.Jit takes there)."""
    residual = P - T
    scale = 1.0 / dr.width(P)
    loss = dr.sum(dr.abs(residual)) * scale
    delta = dr.sign(residual) * scale
    if primal:
        delta = dr.select(residual == 0, 0.0, delta)
    return loss, delta


def unweighted(stage, optimize) -> str | None:
    """Why :func:`recorded_l1` cannot stand for :func:`view_l1` on ``stage``: it weighs every pixel
    alike, so not with the stage's pixel weights (None without them)."""
    return "pixel weights (its recorded form weighs every pixel alike)" if stage.weights else None


LOSS = Loss("l1", "image L1", view_l1, recorded=RecordedLoss(recorded_l1, unweighted))
