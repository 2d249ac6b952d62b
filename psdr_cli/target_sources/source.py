"""The interface every source of target images implements, and what a source gives.

A source is a :class:`TargetSource`: its name, whether an experiment's ``optimize`` section names
it, and

    read(exp) -> TargetInputs                      what the targets come from, read and checked
                                                   (nothing written: a bad input fails before
                                                   the run folder is touched)
    load(exp, files, inputs) -> [image per view]   the target images (H, W, 3), linear RGB (a
                                                   source may render them and cache them in the
                                                   run folder ``files``)
    initial(exp, inputs) -> (V, F, UV) or None     the source's own initial shape when
                                                   ``optimize.init`` is not given (None: a sphere
                                                   around the ground truth, or ``init``)

A source with experiment-file keys of its own (beyond ``optimize.target.images``, ``mesh`` and
``dataset``) declares them in ``keys``, {key: parser factory(base folder)} (the value parsers of
:mod:`psdr_cli.config.values`); the registry registers them with the config package, which then
parses ``optimize.target.KEY`` into ``optimize.target_keys[KEY]``.

Each source module declares its ``SOURCE``; :mod:`.registry` lists them.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, NamedTuple


@dataclass
class TargetMasks:
    """The targets' (H, W) masks in [0, 1], and per view the weight of each pixel in the L1 loss
    (None: 1 everywhere; 0 where a photograph's colour mixes object and background)."""
    masks: list
    weights: list | None = None


class TargetInputs(NamedTuple):
    """What a run's targets come from: the target images (with their cameras when they carry
    them), or the ground truth (V, F) the targets are rendered from; for a fresh run, its initial
    shape (V, F, UV or None: :func:`psdr_cli.optimisation.start_state.initial_shape_uv`); the targets' (H, W) masks
    when every photograph of a dataset has one (else None); and what the source read that its
    initial shape needs (a dataset's views); for a fresh run, the starting values of unknowns
    other than the shape that were found with it (the pose corrections that make a dataset's
    masks agree: :mod:`psdr_cli.optimisation.silhouette_alignment`)."""
    images: list | None
    cameras: list | None
    reference: tuple | None
    initial: tuple | None = None
    masks: TargetMasks | None = None
    views: list | None = None
    initial_values: dict | None = None


def no_initial(exp, inputs: TargetInputs):
    """No initial shape of the source's own (the default of :attr:`TargetSource.initial`)."""
    return None


def given_images(exp, files, inputs: TargetInputs) -> list:
    """The images ``read`` found (the :attr:`TargetSource.load` of a source of finished images)."""
    return inputs.images


@dataclass(frozen=True)
class TargetSource:
    """One source of target images (module docstring)."""
    name: str
    given: Callable[..., bool]        # given(optimize): whether the experiment's optimize section names it
    read: Callable[..., TargetInputs]
    load: Callable[..., list] = given_images
    initial: Callable[..., tuple | None] = no_initial
    keys: dict = field(default_factory=dict)  # its own optimize.target keys: {key: parser factory(base)}
