"""The silhouette loss of a masked photograph: the mean absolute difference of the rendered
coverage C (the share of a pixel's camera rays that hit the scene:
:mod:`psdr_cli.estimators.coverage`) and the mask M,

    L_s = mean |C − M|,   ∂L_s = mean sign(C − M)·∂C.

C's primal value is a Monte Carlo mean, exact only in the limit, so the sign is taken from that
primal (as :func:`.l1.l1_loss` does without an adjoint render); its derivative ∂C comes only from
the silhouettes (C is piecewise constant in the scene's parameters elsewhere).

The loss has no recorded form (:class:`.loss.RecordedLoss`): C is a render of its own, which the
recorded iteration does not make, so a run on masked views is traced.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from .loss import Loss, ViewImages


def silhouette_loss(coverage: mi.Float, mask: mi.Float) -> mi.Float:
    """L_s = mean |C − M| (module docstring), flat W·H arrays."""
    return dr.mean(dr.abs(coverage - mask))


def view_silhouette(view: ViewImages, optimize) -> mi.Float | None:
    """w · L_s of a masked view, w = ``optimize.target.dataset.silhouette`` (None without a mask
    or with w = 0)."""
    weight = optimize.target_dataset.silhouette if optimize.target_dataset else 0.0
    if view.mask is None or not weight > 0:
        return None
    return weight * silhouette_loss(view.coverage(), view.mask)


def has_masks(stage, optimize) -> bool:
    """Whether the stage has masks: the loss may apply (with w = 0 its value is None)."""
    return stage.masks is not None


LOSS = Loss("silhouette", "silhouette", view_silhouette, applies=has_masks)
