"""The unknowns an optimisation may recover, in :data:`NAMES` order: the order in which a problem
makes them, writes them into the scene and saves them.

The module of this package with each name declares its :class:`~.unknown.Unknown` subclass as
``UNKNOWN``. Adding an unknown is its module plus its name in :data:`NAMES`.
"""
from __future__ import annotations

from importlib import import_module

from .unknown import Unknown

#: The unknowns, by module name, in the order a problem holds them (the shape first).
NAMES = ("shape", "albedo", "environment_rotation", "environment_map", "materials", "cameras")

#: The unknowns' classes, in :data:`NAMES` order.
UNKNOWNS: tuple[type[Unknown], ...] = tuple(import_module(f"{__package__}.{name}").UNKNOWN for name in NAMES)


def wanted(cfg) -> list:
    """The classes of the unknowns the ``optimize`` section ``cfg`` asks for, in order."""
    return [kind for kind in UNKNOWNS if kind.wanted(cfg)]


def _check():
    misnamed = [(n, x.name) for n, x in zip(NAMES, UNKNOWNS) if n != x.name]
    if misnamed:
        raise RuntimeError(f"optimisation/unknowns/{misnamed[0][0]}.py declares UNKNOWN named {misnamed[0][1]!r}")


_check()
