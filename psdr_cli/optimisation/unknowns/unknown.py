"""The interface every unknown of an optimisation implements: the shape, the albedo (or its
texture), the environment's rotation, the environment map, the materials, the views' pose
corrections, and any unknown added the README's way.

An unknown is a subclass of :class:`Unknown`. Its class says whether an experiment asks for it
(:meth:`Unknown.wanted`) and what it puts into the scene before the scene is built
(:meth:`Unknown.staged`: a texture's initial texels); an instance, made from the built scene
(:class:`Start`), holds its optimiser entries and knows

- its initial value (the constructor: the saved value, else the experiment's ``init``),
- how it writes itself into the scene (:meth:`~Unknown.scene_values`, AD-attached, then
  :meth:`~Unknown.after_write`; :meth:`~Unknown.write_saved`, a saved value without AD), and
  when that form changes (:meth:`~Unknown.begin`),
- its step (:meth:`~Unknown.step`: ranges, normalisation, an optimiser of its own), its prior,
- its saved values (:meth:`~Unknown.values`, the keys of ``state.npz``'s ``value_*``) and Adam
  entries (:meth:`~Unknown.entries`, ``adam_*``), its textures (:meth:`~Unknown.textures`,
  carried through a remesh),
- its checkpoint files (:meth:`~Unknown.checkpoint_files`, written by
  :func:`psdr_cli.run_folder.checkpoints.write_checkpoint`), its lines of ``optimize.json``
  (:meth:`~Unknown.summary`) and its export (:meth:`~Unknown.export`),
- its release (:meth:`~Unknown.detach`: the scene detached from the optimiser's AD graph).

:class:`psdr_cli.optimisation.problem.Problem` holds the unknowns the experiment asks for, in
:data:`psdr_cli.optimisation.unknowns.registry.NAMES` order, and calls them; no module outside
the optimisation package writes their state. Every method has a default (nothing to write, give
or do), so an unknown implements what concerns it only.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import drjit as dr
import numpy as np


@dataclass
class Shape:
    """The shape being optimised: vertices, faces and per-vertex UVs (or None); with a saved
    state, the "large steps" latent ``u`` and the vertices its basis was built from (``basis``;
    None: ``V``)."""
    V: np.ndarray
    F: np.ndarray
    uv: np.ndarray | None = None
    u: np.ndarray | None = None
    basis: np.ndarray | None = None


@dataclass
class Start:
    """What an unknown starts from: the scene source (:class:`~psdr_cli.optimisation.problem.SceneSource`:
    the scene section, the experiment file, the ``optimize`` section), the shape, the saved values
    (as :meth:`Unknown.values` gives them; {} for a fresh start), the remesh stage, the bitmap
    settings textures are looked up with (None without a texture) and, once the scene is built,
    the scene, its Mitsuba parameters and the Adam optimiser the unknowns share."""
    source: object
    shape: Shape
    values: dict
    stage: int = 0
    lookup: object = None
    scene: object = None
    params: object = None
    opt: object = None

    @property
    def cfg(self):
        """The ``optimize`` section."""
        return self.source.optimize

    @property
    def file(self):
        """The experiment file (named in messages)."""
        return self.source.file


@dataclass(frozen=True)
class Saved:
    """What a saved state holds of the unknowns: the shape's vertices ``V`` and the other unknowns'
    values (as :meth:`Unknown.values` gives them)."""
    V: np.ndarray
    values: dict = field(default_factory=dict)


@dataclass(frozen=True)
class At:
    """The iteration an Adam step belongs to: its number, the run's length and where one-line
    warnings go."""
    iteration: int
    total: int
    warn: object = print


class Unknown:
    """One unknown of an optimisation (module docstring). ``name``: its module's name in the
    registry; ``leaf_form``: whether :meth:`scene_values` may be written as AD leaves (the recorded
    iteration's form, :meth:`psdr_cli.optimisation.problem.Problem.apply_leaves`);
    ``keeps_moments``: whether its Adam moments go on across a remesh (its variables are the same
    after one)."""
    name = "unknown"
    leaf_form = True
    keeps_moments = False

    @staticmethod
    def wanted(cfg) -> bool:
        """Whether the ``optimize`` section ``cfg`` asks for this unknown."""
        return False

    @classmethod
    def staged(cls, built, start: Start):
        """The scene source ``built`` with what the scene must hold before it is built (a texture's
        initial texels); by default ``built`` itself."""
        return built

    def __init__(self, start: Start):
        self.start = start

    def entries(self) -> dict:
        """{saved name: (Adam optimiser, key)} of its variables, the names of ``state.npz``'s
        ``adam_<name>_*``."""
        return {}

    def scene_values(self) -> dict:
        """{Mitsuba parameter: its value from the variables, AD-attached}."""
        return {}

    def after_write(self, scene):
        """After :meth:`scene_values` were written and the parameters updated (the scene's own
        copy of what it wrote)."""

    def write_saved(self, saved: Saved):
        """Write the saved value ``saved`` into the scene without AD (no ``params.update()``)."""

    def begin(self, iteration: int, total: int) -> bool:
        """Before iteration ``iteration`` of ``total``: whether the form of :meth:`scene_values`
        changes from now on (the scene is then written anew)."""
        return False

    def step(self, at: At):
        """After the shared Adam's step (clamps, normalisations, an optimiser of its own)."""

    def prior(self):
        """Its prior's loss term (AD), or None."""
        return None

    def values(self) -> dict:
        """{saved name: numpy array}: what ``state.npz`` keeps of it (``value_<name>``)."""
        return {}

    def textures(self) -> dict:
        """{saved name: (H, W, C) image as the scene uses it} of its textures (carried through a
        remesh: :func:`psdr_cli.optimisation.problem.retextured`)."""
        return {}

    def checkpoint_files(self, files, iteration: int) -> list:
        """Its files of checkpoint ``iteration`` in the run folder ``files`` (records of
        :mod:`psdr_cli.run_folder.checkpoints`: ``Mesh``, ``Picture``, ``CameraPoses``)."""
        return []

    def summary(self, files) -> dict:
        """Its entries of ``optimize.json``'s ``values``: numbers, or the file holding it."""
        return {}

    def detach(self):
        """Write its scene parameters without AD (the end of a run; ``params.update()`` follows)."""

    @staticmethod
    def export(asset, state, exp, where):
        """Put what a finished run recovered of it (``state``: its saved
        :class:`~psdr_cli.run_folder.state.State`, read from ``where``) into ``asset``
        (:class:`~.asset.Asset`) for ``psdr export``; ``exp``: the run's experiment, or None. Called
        for every registered unknown, recovered by the run or not."""


def detached(params, key: str):
    """Write ``params[key]`` without its AD graph."""
    params[key] = dr.detach(params[key])
