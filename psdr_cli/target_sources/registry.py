"""The sources of target images, in :data:`NAMES` order: an experiment's targets come from the
first whose ``given`` holds for its ``optimize`` section (``mesh``, the default, last).

The module of this package with each name declares its :class:`~.source.TargetSource` as
``SOURCE``. Adding a source is its module plus its name in :data:`NAMES`; the keys a source
declares (``TargetSource.keys``) are registered with :mod:`psdr_cli.config.optimize_section` here.
"""
from __future__ import annotations

from importlib import import_module

from ..config.optimize_section import register_target_keys
from .source import TargetSource

#: The sources, by module name, in the order they are asked.
NAMES = ("camera_dataset", "exr_files", "rendered_mesh")

#: The sources, in :data:`NAMES` order.
SOURCES: tuple[TargetSource, ...] = tuple(import_module(f"{__package__}.{name}").SOURCE for name in NAMES)


def _register():
    for source in SOURCES:
        register_target_keys(source.keys)


_register()


def target_source(optimize) -> TargetSource:
    """The source of the targets of an experiment's ``optimize`` section."""
    return next(s for s in SOURCES if s.given(optimize))
