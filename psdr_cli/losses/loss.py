"""The interface every loss of an optimisation implements, as each term of dI/dθ implements
:class:`psdr_cli.estimators.term.Term`.

A loss is a :class:`Loss`: its name, the words it adds to the loss plot's axis label, and
``value``, its contribution for one view of an iteration's mini-batch:

    value(view: ViewImages, optimize: OptimizeConfig) -> mi.Float | None

(None: the loss does not apply to this run or view). The iteration adds value / batch size to
its loss for every loss of :mod:`.registry`, in that order. Each loss module declares its
``LOSS``.

The recorded iteration (:mod:`psdr_cli.optimisation.frozen_batch`, replayed by ``dr.freeze``) asks two more
things of a loss before anything renders:

    applies(stage, optimize: OptimizeConfig) -> bool

whether ``value`` may give a value for the views of a run on ``stage`` (a
:class:`psdr_cli.optimisation.stages.Stage`; false promises None for every view; by default true), and
``recorded``, the loss in the form that iteration evaluates (:class:`RecordedLoss`), or None: it
has none, and every run the loss applies to is traced. That iteration sums the recorded form of
every loss that applies, so a loss with one answers ``applies`` exactly (true only where ``value``
gives values); one without may answer true where it is unsure.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import mitsuba as mi


@dataclass
class ViewImages:
    """What the losses see of one view of the mini-batch (flat arrays)."""
    image: mi.Float                     # the AD render I (W·H·3)
    target: mi.Float                    # its target T (W·H·3)
    adjoint: mi.Float | None            # an independent primal render P (optimize.adjoint_spp), or None
    weight: mi.Float | None             # per-pixel weights of the stage, or None
    mask: mi.Float | None               # the photograph's mask M (W·H, masked datasets), or None
    coverage: Callable[[], mi.Float]    # renders the view's coverage C (W·H, AD) when a loss needs it


def every_stage(stage, optimize) -> bool:
    """True: the loss may apply to any run."""
    return True


def no_refusal(stage, optimize) -> None:
    """None: the recorded form stands for the loss on any stage."""
    return None


@dataclass(frozen=True)
class RecordedLoss:
    """A loss as the recorded iteration evaluates it, over the whole mini-batch at once:

        value_and_adjoint(P, T, primal: bool) -> (ℓ, δ)

    P is the batch's primal render and T its targets, flat (B·W·H·3, view-major); ℓ is the mean
    over the B views of the loss (a one-element mi.Float) and δ = ∂ℓ/∂I its derivative with
    respect to the batch's AD render I, flat as P. ``primal`` true: P is I's own primal value (no
    adjoint render), and δ must be the derivative the traced ``value`` takes at I = P; false: P
    is an independent render, and δ the derivative ``value`` takes with that adjoint render.
    It runs inside ``dr.freeze``: Dr.Jit arithmetic only, no branch on an array's values and no
    read of one on the host.

        refusal(stage, optimize) -> str | None

    says why ``value_and_adjoint`` cannot stand for ``value`` on a run on ``stage`` (None: it
    can; by default it always can): it takes no pixel weights, for one."""
    value_and_adjoint: Callable[[mi.Float, mi.Float, bool], tuple]
    refusal: Callable[..., str | None] = no_refusal


@dataclass(frozen=True)
class Loss:
    """One loss of an optimisation (module docstring)."""
    name: str
    label: str                          # its words in the loss plot's label, e.g. "image L1"
    value: Callable[..., mi.Float | None]
    applies: Callable[..., bool] = every_stage
    recorded: RecordedLoss | None = None

    def recording_refusal(self, stage, optimize) -> str | None:
        """Why the recorded iteration cannot take this loss on a run on ``stage``: it applies and
        has no recorded form, or its form refuses the stage. None: it can, or the loss does not
        apply."""
        if not self.applies(stage, optimize):
            return None
        if self.recorded is None:
            return f"loss {self.name!r} has no recorded form"
        reason = self.recorded.refusal(stage, optimize)
        return None if reason is None else f"loss {self.name!r}: {reason}"
