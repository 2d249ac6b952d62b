"""The interface every loss of an optimisation implements, as each term of dI/dθ implements
:class:`psdr_cli.estimators.term.Term`.

A loss is a :class:`Loss`: its name, the words it adds to the loss plot's axis label, and
``value``, its contribution for one view of an iteration's mini-batch:

    value(view: ViewImages, optimize: OptimizeConfig) -> mi.Float | None

(None: the loss does not apply to this run or view). The iteration adds value / batch size to
its loss for every loss of :mod:`.registry`, in that order. Each loss module declares its
``LOSS``.
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


@dataclass(frozen=True)
class Loss:
    """One loss of an optimisation (module docstring)."""
    name: str
    label: str                          # its words in the loss plot's label, e.g. "image L1"
    value: Callable[..., mi.Float | None]
