"""The losses an optimisation sums for every view of its mini-batch, in :data:`NAMES` order,
traced (:func:`view_losses`) or recorded (:func:`recording_refusal`, :func:`recorded_names`,
:func:`recorded_sum`).

The module of this package with each name declares its :class:`~.loss.Loss` as ``LOSS``.
Adding a loss is its module plus its name in :data:`NAMES`.
"""
from __future__ import annotations

from importlib import import_module

import drjit as dr
import mitsuba as mi

from .loss import Loss, ViewImages

#: The losses, by module name, in the order they are added.
NAMES = ("l1", "silhouette")

#: The losses, in :data:`NAMES` order.
LOSSES: tuple[Loss, ...] = tuple(import_module(f"{__package__}.{name}").LOSS for name in NAMES)

#: The loss plot's axis label: the first loss, then the others and the unknowns' priors.
PLOT_LABEL = f"loss ({LOSSES[0].label}, and any {' or '.join([x.label for x in LOSSES[1:]] + ['prior'])} terms)"


def view_losses(view: ViewImages, optimize):
    """The value of each loss that applies to ``view`` (:class:`~.loss.Loss`), in order."""
    for loss in LOSSES:
        value = loss.value(view, optimize)
        if value is not None:
            yield value


def recording_refusal(stage, optimize) -> str | None:
    """Why the recorded iteration cannot take the losses of a run on ``stage``: the first loss's
    reason (:meth:`~.loss.Loss.recording_refusal`), or None."""
    for loss in LOSSES:
        reason = loss.recording_refusal(stage, optimize)
        if reason is not None:
            return reason
    return None


def recorded_names(stage, optimize) -> tuple[str, ...]:
    """The names of the losses that apply to a run on ``stage``, in order, for
    :func:`recorded_sum`; ValueError where :func:`recording_refusal` gives a reason (a loss would
    be left out)."""
    reason = recording_refusal(stage, optimize)
    if reason is not None:
        raise ValueError(f"the recorded iteration cannot take this run's losses: {reason}")
    return tuple(loss.name for loss in LOSSES if loss.applies(stage, optimize))


def recorded_sum(names: tuple[str, ...], P: mi.Float, T: mi.Float, primal: bool) -> tuple:
    """(Σ_k ℓ_k, Σ_k δ_k) of the recorded forms of the losses ``names`` (:func:`recorded_names`)
    on the batch's render P and targets T (:class:`~.loss.RecordedLoss`): the loss the traced
    iteration sums, and its derivative with respect to the AD render. No loss: (0, 0)."""
    forms = [loss.recorded for loss in LOSSES if loss.name in names]
    if not forms:
        return mi.Float(0.0), dr.zeros(mi.Float, dr.width(P))
    loss, delta = forms[0].value_and_adjoint(P, T, primal)
    for form in forms[1:]:
        value, adjoint = form.value_and_adjoint(P, T, primal)
        loss, delta = loss + value, delta + adjoint
    return loss, delta


def _check():
    misnamed = [(n, x.name) for n, x in zip(NAMES, LOSSES) if n != x.name]
    if misnamed:
        raise RuntimeError(f"losses/{misnamed[0][0]}.py declares LOSS {misnamed[0][1]!r}")


_check()
