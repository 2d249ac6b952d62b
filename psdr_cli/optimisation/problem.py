"""The differentiable state of an optimisation: the scene being optimised, the unknowns the
experiment asks for (:mod:`psdr_cli.optimisation.unknowns`: the shape's "large steps" latent
u = (I + λL) x, and any of the albedo or its texture, the environment's rotation or map, the
materials, the views' pose corrections) and the Adam optimiser they share. Owns the scene's
parameters while a run holds it: only the unknowns write them, through :class:`Problem`."""
from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

from ..config.optimize_section import OptimizeConfig, needs_uv, unwrap_size
from ..config.scene_section import SceneConfig
from ..geometry import atlas
from ..geometry.remesh import remesh
from ..run_folder.state import State
from ..scene.build import build_scene
from ..scene.material_params import texture_lookup
from ..scene.meshes import weld_vertices
from ..support.jitarray import jit_array
from .outlier_clip import clip_outliers
from .stages import stage_at, stage_value
from .unknowns import registry
from .unknowns.unknown import At, Saved, Shape, Start

__all__ = ["Problem", "SceneSource", "Shape", "Saved", "At", "remeshed_problem", "adam_export", "adam_import"]


@dataclass(frozen=True)
class SceneSource:
    """What a problem builds its scene from, rather than the whole experiment: the loaded scene
    section (an XML scene read, split OBJ objects expanded), the experiment file (relative paths
    and messages) and the ``optimize`` section (the object and its unknowns). These are all that
    :func:`psdr_cli.scene.build.build_scene` and :mod:`psdr_cli.scene.material_params` read of an experiment."""
    scene: SceneConfig
    file: Path
    optimize: OptimizeConfig

    @staticmethod
    def of(exp) -> "SceneSource":
        return SceneSource(exp.scene, exp.file, exp.optimize)


class Problem:
    """The scene being optimised, its unknowns (``unknowns``, in
    :data:`~psdr_cli.optimisation.unknowns.registry.NAMES` order, the shape first) and their shared
    Adam optimiser ``opt``.

    Built from a :class:`SceneSource` (the scene it describes, at the film of remesh stage
    ``stage``), a :class:`Shape` and the saved values of the other unknowns (``values``, as
    :meth:`values` gives them; {} for their initial values); ``cameras`` replace the scene's."""

    def __init__(self, source: SceneSource, shape: Shape, cameras, values: dict, stage: int = 0):
        self.source, self.cfg, self.file = source, source.optimize, source.file
        self._applied = None  # the optimiser's variables last written into the scene (apply)
        self._applied_values = {}  # and the values written (the unknowns' scene_values)
        self._leaves = None  # or the leaves written in their place (apply_leaves)
        self._use_leaves = False  # the form apply writes by default (the loop's last iteration's)
        self.factor = stage_value(self.cfg.downsample, stage)
        kinds = registry.wanted(self.cfg)
        start = Start(source, shape, values, stage, texture_lookup(source) if needs_uv(self.cfg) else None)
        self.lookup = start.lookup  # how the textures are looked up
        built = stage_experiment(source, stage)
        for kind in kinds:  # what the scene holds before it is built (a texture's initial texels)
            built = kind.staged(built, start)
        mesh = (shape.V, shape.F) if shape.uv is None else (shape.V, shape.F, np.asarray(shape.uv, np.float64))
        self.scene = build_scene(built, cameras=cameras, objects={self.cfg.object: mesh})
        self.params = mi.traverse(self.scene.mi_scene)
        self.opt = mi.ad.Adam(lr=self.cfg.learning_rate, uniform=True)
        start.scene, start.params, start.opt = self.scene, self.params, self.opt
        self.unknowns = [kind(start) for kind in kinds]
        self.shape = self.unknowns[0]

    @classmethod
    def from_state(cls, source: SceneSource, state: State, cameras) -> "Problem":
        """The problem of a saved (or initial) state, its Adam moments restored: the shape of
        iteration ``state.iteration`` before its remesh, if one is due (the stage of the
        iteration before)."""
        problem = cls(source, Shape(state.V, state.F, state.uv, state.u, state.basis), cameras, state.values,
                      stage=stage_at(source.optimize, max(state.iteration - 1, 0)))
        problem.import_moments(state.adam)
        return problem

    def unknown(self, name: str):
        """The unknown of that registry name, or None when the experiment does not ask for it."""
        return next((u for u in self.unknowns if u.name == name), None)

    @property
    def cameras(self):
        """The views' pose corrections (:class:`~psdr_cli.optimisation.camera_refinement.CameraCorrections`), or None."""
        cams = self.unknown("cameras")
        return cams.corrections if cams is not None else None

    @property
    def key(self) -> str:
        """The scene parameter of the object's vertices."""
        return self.shape.key

    @property
    def F(self) -> np.ndarray:
        return self.shape.F

    @property
    def uv(self):
        """The shape's per-vertex UVs, or None."""
        return self.shape.uv

    @property
    def steps(self):
        """The shape's ``mi.ad.LargeSteps``."""
        return self.shape.steps

    @property
    def basis(self) -> np.ndarray:
        return self.shape.basis

    def entries(self) -> dict:
        """{saved name: (Adam optimiser, key)} of every unknown's variables, in order."""
        return {name: entry for u in self.unknowns for name, entry in u.entries().items()}

    def import_moments(self, saved: dict):
        """Restore the saved Adam moments {saved name: (t, m, v)} of the entries there are."""
        entries = self.entries()
        for name, moments in saved.items():
            if name in entries:
                adam_import(*entries[name], moments)

    def begin(self, iteration: int, total: int):
        """Before iteration ``iteration`` of a ``total``-iteration run: each unknown told (the
        cameras start moving on their schedule; the scene is then written anew)."""
        for u in self.unknowns:
            if u.begin(iteration, total):
                self.invalidate()

    def write_as_leaves(self, leaves: bool):
        """The form :meth:`apply` writes by default from now on (the loop's iteration's form)."""
        self._use_leaves = leaves

    def invalidate(self):
        """The scene no longer holds the optimiser's variables as :meth:`apply` wrote them (a
        backward pass used their AD graph up, or the scene was written otherwise): the next
        :meth:`apply` writes them anew."""
        self._applied = None

    def apply(self, leaves: bool | None = None):
        """Write every unknown into the scene (:meth:`Unknown.scene_values`): AD-attached, or those
        whose ``leaf_form`` allows as AD leaves (detached copies with gradients enabled,
        :meth:`apply_leaves`) when ``leaves`` (None: as the loop's last iteration wanted,
        :meth:`write_as_leaves`); then ``params.update()`` and each unknown's ``after_write``.
        Nothing is done when the variables written last are still the optimiser's, in the same
        form, and their AD graph is unused (the loop applies after each step, for the checkpoint
        and the state, and again when the next iteration starts); a backward pass, :meth:`release`
        or a direct write of ``params`` must :meth:`invalidate`."""
        leaves = self._use_leaves if leaves is None else leaves
        if self.applied_current() and (self._leaves is not None) == leaves:
            return
        current = self.variables()
        self._applied = None
        leafable, direct = {}, {}
        for u in self.unknowns:
            (leafable if u.leaf_form else direct).update(u.scene_values())
        self._applied_values = leafable
        self._leaves = {key: leaf(value) for key, value in leafable.items()} if leaves else None
        for key, value in (self._leaves or leafable).items():
            self.params[key] = value
        for key, value in direct.items():
            self.params[key] = value
        self.params.update()
        for u in self.unknowns:
            u.after_write(self.scene)
        self._applied = current  # held, so that `is` above cannot match a recycled object

    def applied_current(self) -> bool:
        """Whether the values :meth:`apply` wrote last are the optimiser's variables as they are
        now, their AD graph unused."""
        current = self.variables()
        return self._applied is not None and len(current) == len(self._applied) and \
            all(a is b for a, b in zip(current, self._applied))

    def variables(self) -> list:
        """The optimisers' variables as they are now (every unknown's Adam entries, in order)."""
        return [opt.state[key][0] for opt, key in self.entries().values()]

    def apply_leaves(self) -> tuple:
        """:meth:`apply` with the optimiser's variables as AD leaves, for a reverse pass that must
        not reach the optimiser through the large-steps solve (:mod:`psdr_cli.optimisation.frozen_batch`).
        Returns (values, leaves): the attached values and the leaves written, for
        :meth:`backward_leaves` (those of the unknowns with ``leaf_form``)."""
        self.apply(leaves=True)
        return self._applied_values, self._leaves

    def backward_leaves(self, values: dict, leaves: dict):
        """Carry the gradients g_k accumulated in the leaves to the optimiser's variables: the
        backward pass of Σ_k Σ values_k · g_k (g_k constant), i.e. ∂L/∂x = Σ_k (∂values_k/∂x)ᵀ g_k."""
        total = None
        for key, value in values.items():
            g = dr.grad(leaves[key])
            flat = value.array if isinstance(value, mi.TensorXf) else dr.ravel(value)
            part = dr.sum(flat * (g.array if isinstance(g, mi.TensorXf) else dr.ravel(g)))
            total = part if total is None else total + part
        if total is not None and dr.grad_enabled(total):
            dr.backward(total)

    def write_saved(self, saved: Saved):
        """Write a saved state of the unknowns into the scene without AD (guides rebuilt from the
        shape and values they were built from); the next :meth:`apply` writes the optimiser's
        variables back."""
        self.invalidate()
        with dr.suspend_grad():
            for u in self.unknowns:
                u.write_saved(saved)
            self.params.update()

    def prior(self):
        """The sum of the unknowns' priors (loss terms, AD; the environment's smoothness), or None."""
        total = None
        for u in self.unknowns:
            term = u.prior()
            if term is not None:
                total = term if total is None else total + term
        return total

    def finite_gradients(self) -> bool:
        """Whether every gradient of the shared optimiser's entries is finite."""
        return all(np.isfinite(np.asarray(dr.grad(self.opt[k]))).all() for k in self.opt.keys())

    def drop_gradients(self):
        """Zero the gradients of every unknown's entries (an update skipped)."""
        for opt, key in self.entries().values():
            dr.set_grad(opt[key], 0.0)

    def step(self, at: At, learning_rate: float | None = None, clip: float | None = None):
        """One Adam step of the shared optimiser (at ``learning_rate`` when given, gradient spikes
        clipped by ``clip``: :mod:`psdr_cli.optimisation.outlier_clip`), then each unknown's own
        (:meth:`Unknown.step`: ranges, the environment's mean, the cameras' optimiser). Adam's
        moments are kept (an assignment of the same shape keeps them)."""
        if learning_rate is not None:
            self.opt.set_learning_rate(learning_rate)
        clip_outliers(self.opt, clip)
        self.opt.step()
        for u in self.unknowns:
            u.step(at)

    def release(self):
        """Detach the scene from the optimiser's AD graph (nothing may linger in Dr.Jit's global
        AD state after a run, e.g. for later forward-mode work in the same process)."""
        self._applied = None
        self._applied_values, self._leaves, self._use_leaves = {}, None, False
        with dr.suspend_grad():
            for u in self.unknowns:
                u.detach()
            self.params.update()
        for opt, key in self.entries().values():
            dr.disable_grad(opt[key])

    def vertices(self) -> np.ndarray:
        """(n, 3) the shape's vertices as the scene holds them."""
        return self.shape.vertices()

    def values(self) -> dict:
        """{saved name: numpy array} of every unknown (``state.npz``'s ``value_*``)."""
        return {name: v for u in self.unknowns for name, v in u.values().items()}

    def textures(self) -> dict:
        """{saved name: (H, W, C) image} of every texture as the scene uses it."""
        return {name: image for u in self.unknowns for name, image in u.textures().items()}

    def checkpoint_files(self, files, iteration: int) -> list:
        """Every unknown's files of checkpoint ``iteration`` (:mod:`psdr_cli.run_folder.checkpoints`)."""
        return [part for u in self.unknowns for part in u.checkpoint_files(files, iteration)]

    def summary(self, files) -> dict:
        """``optimize.json``'s ``values``: each unknown's numbers, or the file holding it."""
        return {name: v for u in self.unknowns for name, v in u.summary(files).items()}

    def export(self, iteration: int, seconds: float) -> State:
        """The saved state after ``iteration`` iterations: the shape, every Adam entry's moments
        and every unknown's values."""
        adam = {name: adam_export(opt, key) for name, (opt, key) in self.entries().items()}
        return State(iteration, self.vertices(), self.F, adam, self.values(), seconds, self.shape.latent(),
                     self.basis, uv=self.uv)


def leaf(value):
    """A detached copy of ``value`` with gradients enabled (an AD leaf)."""
    x = dr.detach(value)
    dr.enable_grad(x)
    return x


def stage_experiment(exp, stage: int):
    """``exp`` (an experiment or a :class:`SceneSource`) with the film of remesh stage ``stage``:
    W/k × H/k pixels for ``downsample`` k (:func:`psdr_cli.optimisation.stages.stage_value`)."""
    k = stage_value(exp.optimize.downsample, stage)
    if k == 1:
        return exp
    return replace(exp, scene=replace(exp.scene, width=exp.scene.width // k, height=exp.scene.height // k))


def adam_export(opt, key):
    """(t, m, v) of one Adam entry as numpy (``mi.ad.Adam.state[key][3]``)."""
    t, m, v, _ = opt.state[key][3]
    return int(np.asarray(t)[0]), np.asarray(m, np.float32), np.asarray(v, np.float32)


def adam_import(opt, key, saved):
    """Restore (t, m, v) into an Adam entry that was just assigned."""
    value, flag, lr, (t0, m0, v0, extra) = opt.state[key]
    t, m, v = saved
    if np.size(m) != np.size(np.asarray(m0)):
        return  # shape changed (remeshed since): start the moments afresh
    def restore(a, like):
        if dr.is_tensor_v(like):  # a texture: (H, W, C)
            return type(like)(np.asarray(a, np.float32).reshape(like.shape))
        return dr.unravel(type(like), jit_array(mi.Float, np.ravel(a))) if dr.depth_v(like) > 1 else jit_array(type(like), np.ravel(a))
    opt.state[key] = (value, flag, lr, (type(t0)([t]), restore(m, m0), restore(v, v0), extra))


def remeshed_problem(problem: Problem, cameras, it: int, warn) -> Problem:
    """The problem of iteration ``it``, a remesh of ``remesh.at``: the current shape remeshed to
    the stage's vertex count, the other unknowns' values carried over, and the Adam moments of
    those that keep them (``keeps_moments``: the cameras'); the old problem is released."""
    cfg = problem.cfg
    k = cfg.remesh.at.index(it)
    say = lambda m: warn(f"iteration {it}: {m}")  # noqa: E731
    V, F = problem.vertices(), problem.F
    if problem.uv is not None:  # split at UV seams: the remeshers want one vertex per position
        V, F = weld_vertices(V, F)
    V2, F2 = remesh(V, F, cfg.remesh.vertices[k], cfg.remesh.method if cfg.remesh.method != "none" else "isotropic",
                    warn=say)
    values, uv2 = problem.values(), None
    if problem.uv is not None:
        V2, F2, uv2, values = retextured(problem, V2, F2, say)
    moments = {name: adam_export(opt, key) for u in problem.unknowns if u.keeps_moments
               for name, (opt, key) in u.entries().items()}
    problem.release()
    remeshed = Problem(problem.source, Shape(V2, F2, uv2), cameras, values, stage=stage_at(cfg, it))
    remeshed.import_moments(moments)
    return remeshed


def retextured(problem: Problem, V, F, warn):
    """(V', F', UV, values) of a remeshed shape (V, F) of a textured problem: an xatlas atlas of
    the new mesh and every texture of the unknowns (:meth:`Problem.textures`: the albedo's, the
    materials') transferred onto it from the current one (:mod:`psdr_cli.geometry.atlas`), the
    other values as they are. Adam's moments of the textures restart (a new :class:`Problem`), as
    the shape's do. Should the unwrap or a transfer fail, the current mesh, UVs and textures are
    kept (with a warning): a remesh never ends a run."""
    lookup = problem.lookup
    old = (problem.vertices(), problem.F, problem.uv)
    images = problem.textures()
    try:
        V2, F2, uv2 = atlas.unwrap(V, F, unwrap_size(problem.cfg))
        moved = {k: atlas.transfer(old, V2, F2, uv2, image, lookup.filter_type, lookup.wrap_mode)
                 for k, image in images.items()}
    except Exception as exc:  # noqa: BLE001 - xatlas or a degenerate atlas: keep the textured mesh
        warn(f"texture transfer after the remesh failed ({type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}); "
             f"keeping the current mesh")
        return (*old, problem.values())
    return V2, F2, uv2, {**problem.values(), **moved}
