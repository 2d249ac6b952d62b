"""The differentiable state of an optimisation: the scene with the current shape, the "large
steps" latent u = (I + λL) x of its vertices, Adam over u and the extra unknowns (albedo or
albedo texture, environment rotation)."""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

from ..config.optimize_section import OptimizeConfig, needs_uv, unwrap_size
from ..config.parameter import ParameterConfig
from ..config.scene_section import SceneConfig
from ..config.scene_ids import emitter_id
from ..config.unknowns import MATERIAL_DEFAULTS, MATERIAL_UNKNOWNS
from ..errors import PsdrError
from ..geometry import atlas
from ..rendering.camera_motion import check_camera_motion, with_all_edges
from ..support.jitarray import jit_array
from .camera_refinement import CameraCorrections
from ..scene.material_params import (bsdf_parameter, material_key, material_texture_experiment, object_bsdf,
                              texture_experiment, texture_lookup)
from ..geometry.parameters import Parameter
from ..geometry.remesh import remesh
from ..run_folder.state import State
from ..scene.build import build_scene, exr_texels
from ..scene.meshes import weld_vertices
from .stages import stage_at, stage_value


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


class Problem:
    """The scene being optimised: Mitsuba scene with the current shape, parameters, optimiser.

    Built from a :class:`SceneSource` (the scene it describes, at the film of remesh stage
    ``stage``), a :class:`Shape` and the saved values of the extra unknowns (``values``, as
    :meth:`values` gives them; {} for their initial values); ``cameras`` replace the scene's."""

    def __init__(self, source: SceneSource, shape: Shape, cameras, values: dict, stage: int = 0):
        self.source, self.cfg, self.file = source, source.optimize, source.file
        self.applied = None  # the optimiser's variables last written into the scene (apply)
        self.applied_values = {}  # and the values written (scene_values)
        self.leaves = None  # or the leaves written in their place (apply_leaves)
        self.use_leaves = False  # the form apply writes by default (the loop's last iteration's)
        self.factor = stage_value(self.cfg.downsample, stage)
        self.uv = None if shape.uv is None else np.asarray(shape.uv, np.float64)
        self.texture = bool(self.cfg.albedo and self.cfg.albedo_texture is not None)
        self.material_textures = {m.name: m.texture for m in self.cfg.material if m.texture is not None}
        self.lookup = texture_lookup(source) if needs_uv(self.cfg) else None  # how the textures are looked up
        self.scene = build_scene(self.scene_experiment(source, stage, values), cameras=cameras,
                                 objects={self.cfg.object: (shape.V, shape.F) if self.uv is None else
                                          (shape.V, shape.F, self.uv)})
        self.params = mi.traverse(self.scene.mi_scene)
        self.key = f"{self.cfg.object}.vertex_positions"
        self.F = np.asarray(shape.F, np.int64)
        self.steps = self.large_steps(shape, stage)
        self.opt = mi.ad.Adam(lr=self.cfg.learning_rate, uniform=True)
        # a resumed run restores u itself: V = solve(u) is then bit-identical to the saved run's
        self.opt["u"] = jit_array(mi.Float, shape.u) if shape.u is not None else \
            self.steps.to_differential(self.params[self.key])
        self.albedo_key = self.envmap = None
        if self.cfg.albedo:
            self.init_albedo(values)
        if self.cfg.envmap_rotation:
            self.init_envmap_rotation(values)
        self.environment = Environment(self.cfg, source.scene.emitters, self.params, values.get("envmap_log")) \
            if self.cfg.envmap else None
        if self.environment:
            self.opt["envmap"] = self.environment.initial
            self.opt.set_learning_rate({"envmap": self.cfg.envmap.learning_rate})
        self.materials = {}  # name -> (scene key, (lo, hi))
        for m in self.cfg.material:
            self.init_material(m, values)
        self.cameras = self.init_cameras(values) if self.cfg.cameras.mode == "on" else None

    def init_cameras(self, values: dict) -> CameraCorrections:
        """``optimize.cameras``: every view's pose correction. A moving camera moves every
        discontinuity it sees, so every object's edges take part in the boundary terms; a shape
        without an edge list in view is refused (:mod:`psdr_cli.rendering.camera_motion`)."""
        with_all_edges(self.scene)
        for view in range(len(self.scene.sensors)):
            try:
                check_camera_motion(self.scene, view)
            except PsdrError as exc:
                raise PsdrError(f"{self.file}: optimize.cameras: {str(exc).split(': ', 1)[-1]}; set "
                                f"optimize.cameras: off") from None
        return CameraCorrections(self.cfg.cameras, self.params, len(self.scene.sensors), values)

    def refine_cameras(self, moving: bool):
        """Whether the next :meth:`apply` writes the cameras with their corrections' AD graph."""
        if self.cameras is not None and self.cameras.attached != moving:
            self.cameras.attached = moving
            self.applied = None

    def scene_experiment(self, source: SceneSource, stage: int, values: dict) -> SceneSource:
        """The source the scene is built from: the film of ``stage`` and, for a recovered
        texture, the object's bitmap holding the saved texture (or its initial colour); the same
        for each recovered material texture (:func:`initial_texels`)."""
        built = stage_experiment(source, stage)
        if needs_uv(self.cfg) and self.uv is None:
            what = "albedo.texture" if self.texture else f"material.{next(iter(self.material_textures))}.texture"
            raise PsdrError(f"{source.file}: optimize.{what}: the shape being optimised has no UV coordinates")
        for m in self.cfg.material:
            if m.texture is not None:
                built = material_texture_experiment(built, m.name, initial_texels(source, m, values.get(m.name)),
                                                    self.lookup)
        if not self.texture:
            return built
        init = values.get("albedo")
        W, H = self.cfg.albedo_texture
        if init is not None:
            init = np.asarray(init, np.float64).reshape(H, W, 3)
        else:
            init = np.broadcast_to(np.asarray(self.cfg.albedo_init or (0.5, 0.5, 0.5), np.float64), (H, W, 3))
        return texture_experiment(built, np.clip(init, 0.0, 1.0))

    def large_steps(self, shape: Shape, stage: int):
        """``mi.ad.LargeSteps`` over the shape, with the stage's λ (its basis kept in ``basis``)."""
        # LargeSteps welds and orders the vertices by position: a resumed run rebuilds it from the
        # same vertices as the original so that the saved u means the same thing
        self.basis = np.asarray(shape.V if shape.basis is None else shape.basis, np.float64)
        return mi.ad.LargeSteps(jit_array(mi.Float, self.basis.ravel()),
                                self.params[f"{self.cfg.object}.faces"], stage_value(self.cfg.lambda_, stage))

    def init_albedo(self, values: dict):
        """``optimize.albedo``: the object's constant reflectance (or base colour), or its texture."""
        suffixes = ("reflectance.data", "base_color.data") if self.texture else \
            ("reflectance.value", "base_color.value")
        keys = [k for k in self.params.keys() if k.startswith(f"{self.cfg.object}.bsdf.") and k.endswith(suffixes)]
        if not keys:
            raise PsdrError(f"{self.file}: optimize.albedo: the object's BSDF has no constant "
                            f"reflectance/base_color to optimise (give 'texture: [W, H]' for a bitmap)")
        self.albedo_key = keys[0]
        if self.texture:  # the scene holds the initial texture already
            self.opt["albedo"] = self.albedo_value(self.texture_image())
        else:
            init = values.get("albedo")
            if init is None:
                init = self.cfg.albedo_init or np.asarray(self.params[self.albedo_key]).ravel()
            self.opt["albedo"] = self.albedo_value(init)
        self.opt.set_learning_rate({"albedo": self.cfg.albedo_learning_rate})

    def init_envmap_rotation(self, values: dict):
        """``optimize.envmap_rotation``: the environment's rotation angle about its axis."""
        self.envmap = Parameter(self.scene, ParameterConfig(kind="envmap_rotate", axis=self.cfg.envmap_axis), self.params)
        init = values.get("envmap_angle")
        self.opt["envmap_angle"] = mi.Float(float(init[0]) if init is not None
                                            else math.radians(self.cfg.envmap_init_deg))
        self.opt.set_learning_rate({"envmap_angle": self.cfg.envmap_learning_rate})

    def init_material(self, m, values: dict):
        """``optimize.material.NAME``: one BSDF parameter, a constant or a texture (the scene holds
        its initial texels already), within its range."""
        key, (lo, hi) = material_key(self.cfg.object, self.file, self.params, m.name, texture=m.texture is not None)
        self.materials[m.name] = key, (lo, hi)
        if m.texture is not None:
            self.opt[m.name] = dr.clip(mi.TensorXf(self.params[key]), lo, hi)
        else:
            init = values.get(m.name)
            init = float(np.ravel(init)[0]) if init is not None else \
                (m.init if m.init is not None else float(np.ravel(self.params[key])[0]))
            self.opt[m.name] = mi.Float(min(max(init, lo), hi))
        self.opt.set_learning_rate({m.name: m.learning_rate})

    @classmethod
    def from_state(cls, source: SceneSource, state: State, cameras) -> "Problem":
        """The problem of a saved (or initial) state, its Adam moments restored: the shape of
        iteration ``state.iteration`` before its remesh, if one is due (the stage of the
        iteration before)."""
        problem = cls(source, Shape(state.V, state.F, state.uv, state.u, state.basis), cameras, state.values,
                      stage=stage_at(source.optimize, max(state.iteration - 1, 0)))
        for k, saved in state.adam.items():
            if k in problem.opt.keys():
                adam_import(problem.opt, k, saved)
            elif problem.cameras and k.startswith("camera_") and k[7:] in problem.cameras.opt.keys():
                adam_import(problem.cameras.opt, k[7:], saved)
        return problem

    def apply(self, leaves: bool | None = None):
        """Write the optimiser's variables into the scene: AD-attached, or as AD leaves (detached
        copies with gradients enabled, :meth:`apply_leaves`) when ``leaves`` (None: as the loop's
        last iteration wanted, ``use_leaves``). Nothing is done when the variables written last
        are still the optimiser's, in the same form, and their AD graph is unused (the loop
        applies after each step, for the checkpoint and the state, and again when the next
        iteration starts); a backward pass, :meth:`release` or a direct write of ``params`` must
        set ``applied = None``."""
        leaves = self.use_leaves if leaves is None else leaves
        if self.applied_current() and (self.leaves is not None) == leaves:
            return
        current = self.variables()
        self.applied = None
        self.applied_values = self.scene_values()
        self.leaves = {key: leaf(value) for key, value in self.applied_values.items()} if leaves else None
        for key, value in (self.leaves or self.applied_values).items():
            self.params[key] = value
        if self.cameras:
            self.cameras.write(self.params)
        if self.envmap:
            self.envmap.apply(self.opt["envmap_angle"])  # calls params.update()
        else:
            self.params.update()
        self.applied = current  # held, so that `is` above cannot match a recycled object

    def applied_current(self) -> bool:
        """Whether the values :meth:`apply` wrote last are the optimiser's variables as they are
        now, their AD graph unused."""
        current = self.variables()
        return self.applied is not None and len(current) == len(self.applied) and \
            all(a is b for a, b in zip(current, self.applied))

    def variables(self) -> list:
        """The optimisers' variables as they are now (the shape's, the extra unknowns', the cameras')."""
        cams = [self.cameras.opt.state[k][0] for k in self.cameras.opt.keys()] if self.cameras else []
        return [self.opt.state[k][0] for k in self.opt.keys()] + cams

    def scene_values(self) -> dict:
        """{scene parameter: its value from the optimiser's variables (AD-attached)}: the vertices
        V = solve(u) of the large steps, the albedo clipped to [0, 1], the environment's texels, the
        materials (the environment's rotation is applied by :meth:`apply` itself)."""
        values = {self.key: self.steps.from_differential(self.opt["u"])}
        if self.albedo_key:  # (re-assigning opt["albedo"] would reset its Adam moments)
            values[self.albedo_key] = dr.clip(self.opt["albedo"], 0.0, 1.0)
        if self.environment:
            values[self.environment.key] = self.environment.texels(self.opt["envmap"])
        for name, (key, _) in self.materials.items():
            values[key] = self.opt[name]  # within its range: after_step clamps it
        return values

    def apply_leaves(self) -> tuple:
        """:meth:`apply` with the optimiser's variables as AD leaves, for a reverse pass that must
        not reach the optimiser through the large-steps solve (:mod:`psdr_cli.optimisation.frozen_batch`).
        Returns (values, leaves): the attached values and the leaves written, for
        :meth:`backward_leaves`. Not with an environment rotation."""
        self.apply(leaves=True)
        return self.applied_values, self.leaves

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

    def prior(self):
        """The loss terms of the unknowns' priors (the environment's smoothness), or None."""
        if self.environment and self.cfg.envmap.smoothness > 0:
            return self.cfg.envmap.smoothness * self.environment.roughness(self.opt["envmap"])
        return None

    def after_step(self):
        """After each Adam step: the material unknowns clamped to their ranges, the environment's
        mean radiance held at its initial value (``optimize.envmap.mean``). Adam's moments are kept
        (an assignment of the same shape keeps them)."""
        for name, (_, (lo, hi)) in self.materials.items():
            self.opt[name] = dr.clip(self.opt[name], lo, hi)
        if self.environment and self.environment.fixed_mean:
            self.opt["envmap"] = self.environment.normalised(self.opt["envmap"])

    def write_values(self, values: dict):
        """Write the environment and material unknowns of ``values`` (as :meth:`values` gives them)
        into the scene, without AD (guides rebuilt from a saved state); no ``params.update()``."""
        if self.environment and "envmap_log" in values:
            self.params[self.environment.key] = self.environment.texels(jit_array(mi.TensorXf, values["envmap_log"]))
        for name, (key, _) in self.materials.items():
            if name in values and name in self.material_textures:
                W, H = self.material_textures[name]
                self.params[key] = jit_array(mi.TensorXf, np.asarray(values[name], np.float64).reshape(H, W, 1))
            elif name in values:
                self.params[key] = mi.Float(float(np.ravel(values[name])[0]))

    def release(self):
        """Detach the scene from the optimiser's AD graph (nothing may linger in Dr.Jit's global
        AD state after a run, e.g. for later forward-mode work in the same process)."""
        self.applied = None
        self.applied_values, self.leaves, self.use_leaves = {}, None, False
        with dr.suspend_grad():
            self.params[self.key] = dr.detach(self.params[self.key])
            if self.albedo_key:
                self.params[self.albedo_key] = dr.detach(self.params[self.albedo_key])
            if self.environment:
                self.params[self.environment.key] = dr.detach(self.params[self.environment.key])
            for key, _ in self.materials.values():
                self.params[key] = dr.detach(self.params[key])
            for k in (self.envmap.keys if self.envmap else ()):
                self.params[k] = mi.AffineTransform4f(dr.detach(self.params[k].matrix))
            if self.cameras:
                self.cameras.detach(self.params)
            self.params.update()
        for k in list(self.opt.keys()):
            dr.disable_grad(self.opt[k])
        for k in list(self.cameras.opt.keys()) if self.cameras else ():
            dr.disable_grad(self.cameras.opt[k])

    def vertices(self) -> np.ndarray:
        return np.asarray(dr.detach(self.params[self.key]), np.float64).reshape(-1, 3)

    def albedo_value(self, a):
        """The albedo ``a`` (numpy, clipped to [0, 1]) as the scene parameter's type: a texture
        (H, W, 3) tensor, an RGB colour, or a grey value (a grey reflectance stays grey)."""
        a = np.clip(np.asarray(a, np.float64), 0.0, 1.0)
        if self.texture:
            return jit_array(mi.TensorXf, a)
        a = a.ravel()
        if isinstance(self.params[self.albedo_key], mi.Color3f):  # RGB texture
            return mi.Color3f(*(float(x) for x in np.broadcast_to(a, 3)))
        return mi.Float(float(a.mean()))

    def texture_image(self) -> np.ndarray:
        """The texture being recovered as the scene uses it: (H, W, 3) linear RGB in [0, 1]."""
        return np.asarray(dr.detach(self.params[self.albedo_key]), np.float64)

    def values(self) -> dict:
        out = {}
        if self.albedo_key:
            a = np.asarray(self.opt["albedo"], np.float64)
            out["albedo"] = a.reshape(self.opt["albedo"].shape) if self.texture else a.ravel()
        if self.envmap:
            out["envmap_angle"] = np.asarray(self.opt["envmap_angle"], np.float64).ravel()
        if self.environment:
            out["envmap_log"] = np.asarray(self.opt["envmap"], np.float64)
        for name in self.materials:
            v = np.asarray(self.opt[name], np.float64)
            out[name] = v.reshape(self.opt[name].shape) if name in self.material_textures else v.ravel()
        if self.cameras:
            out.update(self.cameras.values())
        return out

    def material_image(self, name: str) -> np.ndarray:
        """The texture of ``optimize.material.NAME`` as the scene uses it: (H, W, 1) in its range."""
        return np.asarray(dr.detach(self.params[self.materials[name][0]]), np.float64)

    def export(self, iteration: int, seconds: float) -> State:
        adam = {k: adam_export(self.opt, k) for k in self.opt.keys()}
        if self.cameras:
            adam.update({f"camera_{k}": adam_export(self.cameras.opt, k) for k in self.cameras.opt.keys()})
        return State(iteration, self.vertices(), self.F, adam, self.values(), seconds,
                     np.asarray(self.opt["u"], np.float32), self.basis, uv=self.uv)


class Environment:
    """``optimize.envmap``: the lat-long map of the scene's ``envmap`` emitter as the unknown
    x (H, W, 3) of log-radiance; the emitter's texels are exp(x) (its ``scale`` and rotation as
    given). Mitsuba's ``data`` is (H, W + 2, 3): one halo column either side, refreshed by the
    emitter from the real columns (each halo's derivative routed onto its source column)."""

    def __init__(self, cfg, emitters: list, params, saved=None):
        """``cfg``: the ``optimize`` section; ``emitters``: the scene's; ``saved``: the saved
        log-radiance, or None for the initial map."""
        optimize, cfg = cfg, cfg.envmap
        index = next(i for i, e in enumerate(emitters) if e.type == "envmap")
        self.key = f"{emitter_id(index)}.data"
        self.W, self.H = cfg.resolution
        scene_map = np.asarray(params[self.key], np.float64)[:, 1:-1]  # the map the scene was built with
        self.weights = solid_angle_weights(self.H, self.W)
        if cfg.init_file is not None:
            start = latlong_resample(np.asarray(exr_texels(cfg.init_file), np.float64)[..., :3], self.W, self.H)
        elif cfg.init is not None:
            start = np.broadcast_to(np.asarray(cfg.init, np.float64), (self.H, self.W, 3))
        else:
            w = solid_angle_weights(*scene_map.shape[:2])
            start = np.broadcast_to((scene_map * w[..., None]).sum((0, 1)) / w.sum(), (self.H, self.W, 3))
        start = np.maximum(start, 1e-4 * max(float(start.max()), 1e-30))  # log-radiance needs > 0
        self.mean = float((start * self.weights[..., None]).sum() / (3 * self.weights.sum()))
        self.fixed_mean = cfg.mean == "fixed" or (cfg.mean == "auto" and optimize.albedo)
        self.initial = jit_array(mi.TensorXf, np.log(start) if saved is None else saved)
        cols = np.concatenate([[self.W - 1], np.arange(self.W), [0]])
        idx = ((np.arange(self.H)[:, None] * self.W + cols[None, :])[..., None] * 3 + np.arange(3)).ravel()
        self.halo = jit_array(mi.UInt32, idx)
        self.w = jit_array(mi.Float, np.repeat(self.weights.ravel() / (3 * self.weights.sum()), 3))
        right = (np.arange(self.W) + 1) % self.W
        a = np.arange(self.H * self.W).reshape(self.H, self.W)
        pairs = np.concatenate([np.stack([a.ravel(), a[:, right].ravel()], 1),
                                np.stack([a[:-1].ravel(), a[1:].ravel()], 1)])
        pairs = (pairs[:, :, None] * 3 + np.arange(3)).transpose(0, 2, 1).reshape(-1, 2)
        self.pairs = (jit_array(mi.UInt32, pairs[:, 0]), jit_array(mi.UInt32, pairs[:, 1]))

    def texels(self, x):
        """Mitsuba's ``data`` tensor (H, W + 2, 3) of the log-radiance x (AD-attached)."""
        flat = dr.gather(mi.Float, dr.exp(x.array), self.halo)
        return mi.TensorXf(flat, (self.H, self.W + 2, 3))

    def radiance(self, x) -> np.ndarray:
        """exp(x) as (H, W, 3) numpy."""
        return np.exp(np.asarray(dr.detach(x), np.float64))

    def normalised(self, x):
        """x shifted so that the solid-angle mean of exp(x) is the initial map's."""
        mean = dr.sum(self.w * dr.exp(dr.detach(x.array)))
        return mi.TensorXf(dr.detach(x.array) - dr.log(mean / self.mean), x.shape)

    def roughness(self, x):
        """Mean squared difference of the log-radiance between neighbouring texels (longitude
        wraps around, latitude does not): the quadratic form of the grid's graph Laplacian."""
        d = dr.gather(mi.Float, x.array, self.pairs[0]) - dr.gather(mi.Float, x.array, self.pairs[1])
        return dr.mean(d * d)


def solid_angle_weights(H: int, W: int) -> np.ndarray:
    """(H, W) solid angles (up to a factor) of the texels of a lat-long map: sin θ of each row."""
    theta = (np.arange(H) + 0.5) / H * np.pi
    return np.broadcast_to(np.sin(theta)[:, None], (H, W)).copy()


def latlong_resample(image, W: int, H: int) -> np.ndarray:
    """A lat-long map (h, w, 3) resampled to (H, W, 3): bilinear at texel centres, longitude
    wrapping around, latitude clamped (the same map when the size is the same)."""
    h, w = image.shape[:2]
    if (h, w) == (H, W):
        return np.asarray(image, np.float64)
    x = (np.arange(W) + 0.5) / W * w - 0.5
    y = np.clip((np.arange(H) + 0.5) / H * h - 0.5, 0, h - 1)
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = (x - x0)[None, :, None], (y - y0)[:, None, None]
    y1 = np.minimum(y0 + 1, h - 1)
    xa, xb = x0 % w, (x0 + 1) % w
    row = lambda r: image[r][:, xa] * (1 - fx) + image[r][:, xb] * fx  # noqa: E731
    return row(y0) * (1 - fy) + row(y1) * fy


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
    the stage's vertex count, the extra unknowns carried over (the old problem is released)."""
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
    moments = {k: adam_export(problem.cameras.opt, k) for k in problem.cameras.opt.keys()} if problem.cameras else {}
    problem.release()
    remeshed = Problem(problem.source, Shape(V2, F2, uv2), cameras, values, stage=stage_at(cfg, it))
    for k, saved in moments.items():  # the poses' moments go on: their unknowns are the same
        adam_import(remeshed.cameras.opt, k, saved)
    return remeshed


def retextured(problem: Problem, V, F, warn):
    """(V', F', UV, values) of a remeshed shape (V, F) of a textured problem: an xatlas atlas of
    the new mesh and every texture (the albedo's, the materials') transferred onto it from the
    current one (:mod:`psdr_cli.geometry.atlas`), the other unknowns as they are. Adam's moments of the
    textures restart (a new :class:`Problem`), as the shape's do. Should the unwrap or a transfer
    fail, the current mesh, UVs and textures are kept (with a warning): a remesh never ends a run."""
    lookup = problem.lookup
    old = (problem.vertices(), problem.F, problem.uv)
    images = {n: problem.material_image(n) for n in problem.material_textures}
    if problem.texture:
        images["albedo"] = problem.texture_image()
    try:
        V2, F2, uv2 = atlas.unwrap(V, F, unwrap_size(problem.cfg))
        moved = {k: atlas.transfer(old, V2, F2, uv2, image, lookup.filter_type, lookup.wrap_mode)
                 for k, image in images.items()}
    except Exception as exc:  # noqa: BLE001 - xatlas or a degenerate atlas: keep the textured mesh
        warn(f"texture transfer after the remesh failed ({type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}); "
             f"keeping the current mesh")
        return (*old, problem.values())
    return V2, F2, uv2, {**problem.values(), **moved}


def initial_texels(exp, m, saved) -> np.ndarray:
    """(H, W, 1) starting texels of the texture of ``optimize.material.NAME`` (``m``): the saved
    ones, else ``init``, the BSDF's own constant or Mitsuba's default, clamped to its range."""
    W, H = m.texture
    (lo, hi), _ = MATERIAL_UNKNOWNS[m.name]
    if saved is not None:
        return np.clip(np.asarray(saved, np.float64).reshape(H, W, 1), lo, hi)
    parameter = bsdf_parameter(exp, m.name)
    given = object_bsdf(exp).params.get(parameter)
    value = m.init if m.init is not None else given if isinstance(given, (int, float)) else MATERIAL_DEFAULTS[parameter]
    return np.full((H, W, 1), min(max(float(value), lo), hi))
