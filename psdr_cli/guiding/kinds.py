"""The guide kinds, in :data:`psdr_cli.config.vocabularies.GUIDE_KINDS` order.

The module of this package with each name declares its :class:`~.guide.GuideKind` as ``KIND``.
Adding a guide kind is its module plus its name in that tuple.
"""
from __future__ import annotations

from importlib import import_module

from ..config.vocabularies import GUIDE_KINDS as NAMES
from .guide import GuideKind

#: The guide kinds, in :data:`NAMES` order.
KINDS: tuple[GuideKind, ...] = tuple(import_module(f"{__package__}.{name}").KIND for name in NAMES)
#: Names of the kinds the optimisation loop fits to its own samples (:mod:`.loop_fed`).
LOOP_FED = tuple(k.name for k in KINDS if k.loop_fed)

_BY_NAME = {k.name: k for k in KINDS}


def guide_kind(name: str) -> GuideKind:
    """The guide kind called ``name``."""
    try:
        return _BY_NAME[name]
    except KeyError:
        raise ValueError(f"unknown guide kind {name!r} (expected one of {', '.join(NAMES)})") from None


def _check():
    misnamed = [(n, k.name) for n, k in zip(NAMES, KINDS) if n != k.name]
    if misnamed:
        raise RuntimeError(f"guiding/{misnamed[0][0]}.py declares KIND {misnamed[0][1]!r}")


_check()
