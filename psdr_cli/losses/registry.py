"""The losses an optimisation sums for every view of its mini-batch, in :data:`NAMES` order.

The module of this package with each name declares its :class:`~.loss.Loss` as ``LOSS``.
Adding a loss is its module plus its name in :data:`NAMES`.
"""
from __future__ import annotations

from importlib import import_module

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


def _check():
    misnamed = [(n, x.name) for n, x in zip(NAMES, LOSSES) if n != x.name]
    if misnamed:
        raise RuntimeError(f"losses/{misnamed[0][0]}.py declares LOSS {misnamed[0][1]!r}")


_check()
