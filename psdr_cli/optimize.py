"""Inverse rendering (``psdr optimize``): reconstruct an object's shape from images.

Each iteration renders a mini-batch of views with the psdr estimator in reverse mode (or with
Mitsuba's projective integrators: ``estimator.engine``, :mod:`psdr_cli.engines`) and takes one
step on the L1 image loss

    L = (1/|B|) Σ_{v ∈ B} mean |I_v(x) − T_v|,

with the vertex positions x parametrised by the "large steps" latent u = (I + λL) x (Nicolet et
al. 2021, ``mi.ad.LargeSteps``) and updated by ``mi.ad.Adam(uniform=True)``. The object's albedo
and the environment's rotation angle can be optimised jointly. The shape is remeshed
(field-aligned, :mod:`psdr_cli.remesh`) before the first iteration and on a schedule.

Nothing already saved is lost: the state (mesh, optimiser moments, iteration) is written
atomically after every iteration, checkpoints and previews at ``checkpoint_every``, and
``resume=True`` continues from the saved state. View batches and sample seeds depend only on
(seed, iteration), so a resumed run draws what the uninterrupted run would have drawn.

An optional wall-clock budget (``optimize.seconds``, optimisation time only) ends a run early,
for equal-time comparisons; ``optimize.variants`` turns one experiment into an ablation whose
runs (estimator overrides) live in ``<output>/<name>/<label>/``
(:func:`psdr_cli.runs.variant_experiments`; the run-folder layout is :mod:`psdr_cli.runs`).
"""
from __future__ import annotations

import glob
import hashlib
import json
import math
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

from . import backend, fileio, meshes, plots
from .config import BitmapConfig, BsdfConfig, CameraConfig, Experiment, ParameterConfig, check_stages
from .engines import Engine
from .errors import PsdrError
from .estimators.boundary_sampling import edge_list
from .estimators.passes import pass_seed
from .estimators.registry import ADJOINT_STREAM
from .gradient import Settings, make_guides, uses_guides
from .jitarray import jit_array
from .parameters import Parameter
from .remesh import remesh
from .render import render_view
from .runs import (RunFiles, append_log, clear_run, lock_run, move_aside, read_log, run_record, same_experiment,
                   scene_identity, variant_experiments, write_log, write_mesh)
from .scene import build_scene, object_mesh


# --------------------------------------------------------------------------------------------
# Ground truth, targets, initial shape
# --------------------------------------------------------------------------------------------
def ground_truth(exp):
    """World-space (V, F) of the target shape: ``target.mesh`` (placed with the object's
    transform) or the object's own mesh in the scene."""
    cfg = exp.optimize
    obj = next(o for o in exp.scene.objects if o.name == cfg.object)
    if cfg.target_mesh is None:
        return object_mesh(obj, str(exp.file))
    V, F = meshes.load_mesh(cfg.target_mesh, str(exp.file))
    return meshes.apply_transform(V, meshes.transform_matrix(obj.transform)), F


def initial_shape(exp, reference):
    """(V, F) of ``init`` (with its transform), or a sphere around the reference's bounding box."""
    return initial_shape_uv(exp, reference)[:2]


def initial_shape_uv(exp, reference):
    """(V, F, UV or None) of the initial shape (:func:`initial_shape`); with ``albedo.texture`` the
    default sphere is a UV sphere, and a given ``init`` must have UVs."""
    cfg = exp.optimize
    texture = cfg.albedo and cfg.albedo_texture is not None
    if cfg.init is not None:
        V, F, uv = meshes.load_mesh_uv(cfg.init, str(exp.file), keep_uv=texture)
        if texture and uv is None:
            raise PsdrError(f"{exp.file}: optimize.init.mesh: has no UV coordinates, which optimize.albedo.texture "
                            f"needs (e.g. {{shape: sphere, resolution: 16, uv: true}}, or an OBJ with 'vt')")
        return meshes.apply_transform(V, meshes.transform_matrix(cfg.init_transform)), F, uv
    if reference is None:
        raise PsdrError(f"{exp.file}: optimize.init: required when the targets are images "
                        f"(e.g. init: {{mesh: {{shape: sphere, radius: 0.5}}}})")
    V, F = reference
    lo, hi = V.min(0), V.max(0)
    radius = 0.5 * float((hi - lo).max())
    Vs, Fs, uv = meshes.uv_sphere(radius, 16) if texture else (*meshes.sphere(radius=radius, subdivisions=3), None)
    return Vs + (lo + hi) / 2, Fs, uv


def target_seed(exp) -> int:
    """Seed of the target renders: the experiment's (for a variant, the base experiment's, so
    that every run of an ablation fits the same images)."""
    return exp.seed if exp.optimize.target_seed is None else exp.optimize.target_seed


def target_key(exp, reference, spp: int) -> str:
    """Hash of everything a cached target image depends on (bitmap textures' contents included)."""
    h = hashlib.sha256()
    h.update(json.dumps(scene_identity(asdict(exp.scene)), default=str, sort_keys=True).encode())
    h.update(np.ascontiguousarray(reference[0], np.float64).tobytes())
    h.update(np.ascontiguousarray(reference[1], np.int64).tobytes())
    h.update(f"{spp}:{target_seed(exp)}".encode())
    for obj in exp.scene.objects:  # the textures' contents (a repainted texture makes new targets)
        for value in obj.bsdf.params.values():
            if isinstance(value, BitmapConfig) and value.file is not None and value.file.is_file():
                h.update(value.file.read_bytes())
    return h.hexdigest()[:16]


def render_targets(exp, files: RunFiles, reference, progress=None):
    """Target images of every view, rendered from the ground truth at ``target.spp`` and cached
    in ``targets/`` (reused while the scene, the ground truth and spp are unchanged)."""
    cfg = exp.optimize
    key = target_key(exp, reference, cfg.target_spp)
    paths = [files.targets / f"view_{v:03d}.exr" for v in range(len(exp.scene.cameras))]
    cached = all(p.exists() for p in paths) and all(
        fileio.read_exr(p)["__header__"].get("psdr.target_key") == key for p in paths)
    if cached:
        return [fileio.read_rgb_exr(p).astype(np.float64) for p in paths]
    scene = build_scene(exp, objects={cfg.object: reference})
    images = []
    for v, p in enumerate(paths):
        image = render_view(scene, v, cfg.target_spp, seed=target_seed(exp) + 7919)
        cam = exp.scene.cameras[v]
        fileio.write_rgb_exr(p, image, {"psdr.target_key": key, "psdr.view": str(v), "psdr.spp": str(cfg.target_spp),
                                    "psdr.camera": {"origin": cam.origin, "target": cam.target, "up": cam.up,
                                                    "fov": cam.fov}})
        fileio.write_preview(p.with_suffix(".png"), image)
        images.append(image)
        if progress:
            progress(v)
    return images


def image_targets(exp):
    """(images, cameras) from ``target.images`` (EXR files written by ``psdr render``)."""
    pattern = exp.optimize.target_images
    paths = sorted(glob.glob(pattern))
    if not paths:
        raise PsdrError(f"{exp.file}: optimize.target.images: no file matches '{pattern}'")
    images, cameras = [], []
    for p in paths:
        try:
            exr = fileio.read_exr(p)
            cam = json.loads(exr["__header__"]["psdr.camera"])
        except KeyError:
            raise PsdrError(f"{p}: no 'psdr.camera' header (target images must come from `psdr render`)") from None
        except Exception as exc:  # noqa: BLE001 - unreadable EXR
            raise PsdrError(f"{p}: cannot read the EXR target ({str(exc).splitlines()[0] if str(exc) else exc})") from None
        image = np.stack([exr["R"], exr["G"], exr["B"]], -1).astype(np.float64)
        if image.shape[:2] != (exp.scene.height, exp.scene.width):
            raise PsdrError(f"{p}: image is {image.shape[1]}×{image.shape[0]}, but scene.film is "
                            f"{exp.scene.width}×{exp.scene.height}")
        images.append(image)
        cameras.append(CameraConfig(origin=tuple(cam["origin"]), target=tuple(cam["target"]),
                                    up=tuple(cam["up"]), fov=float(cam["fov"])))
    return images, cameras


# --------------------------------------------------------------------------------------------
# Optimisation state
# --------------------------------------------------------------------------------------------
@dataclass
class State:
    """Everything needed to continue a run: mesh, optimiser moments, extra unknowns."""
    iteration: int
    V: np.ndarray
    F: np.ndarray
    adam: dict = field(default_factory=dict)     # name -> (t, m, v)
    values: dict = field(default_factory=dict)   # extra unknowns: albedo (3,), envmap angle (1,)
    seconds: float = 0.0                         # optimisation time so far
    u: np.ndarray | None = None                  # large-steps latent (V = solve(u) reproduces the saved V exactly)
    basis: np.ndarray | None = None              # vertices LargeSteps was built from (orders u)
    guide_V: np.ndarray | None = None            # vertices the current guides were built from
    guide_values: dict = field(default_factory=dict)  # extra unknowns when they were built
    uv: np.ndarray | None = None                 # per-vertex texture coordinates (albedo.texture)

    def save(self, path: Path):
        """Written atomically; refuses NaN or infinite values (nothing non-finite is ever saved)."""
        arrays = {"V": self.V, "F": self.F, "u": self.u, "basis": self.basis}
        if self.uv is not None:
            arrays["uv"] = self.uv
        if self.guide_V is not None:
            arrays["guide_V"] = self.guide_V
            for k, v in self.guide_values.items():
                arrays[f"guidevalue_{k}"] = v
        for k, (t, m, v) in self.adam.items():
            arrays[f"adam_{k}_m"], arrays[f"adam_{k}_v"] = m, v
        for k, v in self.values.items():
            arrays[f"value_{k}"] = v
        for k, a in arrays.items():
            fileio.check_finite(path, a, f"state '{k}'")
        meta = {"iteration": self.iteration, "seconds": self.seconds,
                "adam_t": {k: int(t) for k, (t, _, _) in self.adam.items()}}
        with fileio.atomic_path(path) as tmp:
            with open(tmp, "wb") as f:
                np.savez(f, meta=np.frombuffer(json.dumps(meta).encode(), np.uint8), **arrays)

    @staticmethod
    def load(path: Path) -> "State":
        try:
            with np.load(path) as z:
                meta = json.loads(bytes(z["meta"]).decode())
                adam = {k: (t, z[f"adam_{k}_m"], z[f"adam_{k}_v"]) for k, t in meta["adam_t"].items()}
                values = {k[6:]: z[k] for k in z.files if k.startswith("value_")}
                guide_values = {k[11:]: z[k] for k in z.files if k.startswith("guidevalue_")}
                state = State(meta["iteration"], z["V"], z["F"], adam, values, meta.get("seconds", 0.0),
                              z["u"], z["basis"], z["guide_V"] if "guide_V" in z.files else None, guide_values,
                              z["uv"] if "uv" in z.files else None)
                arrays = [state.V, state.u, state.basis, *values.values(), *([state.uv] if state.uv is not None else []),
                          *(a for _, m, v in adam.values() for a in (m, v))]
        except Exception as exc:  # noqa: BLE001 - a damaged state file
            raise PsdrError(f"{path}: cannot read the saved state ({type(exc).__name__}); "
                            f"delete it to start over") from None
        if not all(np.isfinite(np.asarray(a, float)).all() for a in arrays):
            raise PsdrError(f"{path}: the saved state holds NaN or infinite values; delete it to start over")
        return state


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


# --------------------------------------------------------------------------------------------
# The optimisation
# --------------------------------------------------------------------------------------------
@dataclass
class OptimizeResult:
    folder: Path
    iterations: int = 0
    resumed_from: int = 0
    losses: list = field(default_factory=list)
    final: Path | None = None
    checkpoints: list = field(default_factory=list)
    interrupted: bool = False
    skipped: int = 0
    budget_stop: bool = False        # the time budget (optimize.seconds) ended the run early
    seconds: float = 0.0             # optimisation seconds of the whole run


class Problem:
    """The scene being optimised: Mitsuba scene with the current shape, parameters, optimiser."""

    def __init__(self, exp, V, F, cameras, state_values: dict, u=None, basis=None, uv=None, stage: int = 0):
        self.exp, self.cfg = exp, exp.optimize
        self.factor = stage_value(self.cfg.downsample, stage)
        self.uv = None if uv is None else np.asarray(uv, np.float64)
        self.texture = bool(self.cfg.albedo and self.cfg.albedo_texture is not None)
        built = stage_experiment(exp, stage)
        if self.texture:
            if self.uv is None:
                raise PsdrError(f"{exp.file}: optimize.albedo.texture: the shape being optimised has no UV coordinates")
            init = state_values.get("albedo")
            W, H = self.cfg.albedo_texture
            if init is not None:
                init = np.asarray(init, np.float64).reshape(H, W, 3)
            else:
                init = np.broadcast_to(np.asarray(self.cfg.albedo_init or (0.5, 0.5, 0.5), np.float64), (H, W, 3))
            built = texture_experiment(built, np.clip(init, 0.0, 1.0))
        mesh = (V, F) if self.uv is None else (V, F, self.uv)
        self.scene = build_scene(built, objects={self.cfg.object: mesh}, cameras=cameras)
        self.params = mi.traverse(self.scene.mi_scene)
        self.key = f"{self.cfg.object}.vertex_positions"
        self.F = np.asarray(F, np.int64)
        # LargeSteps welds and orders the vertices by position: a resumed run rebuilds it from the
        # same vertices as the original so that the saved u means the same thing
        self.basis = np.asarray(V if basis is None else basis, np.float64)
        self.steps = mi.ad.LargeSteps(jit_array(mi.Float, self.basis.ravel()),
                                      self.params[f"{self.cfg.object}.faces"], stage_value(self.cfg.lambda_, stage))
        self.opt = mi.ad.Adam(lr=self.cfg.learning_rate, uniform=True)
        # a resumed run restores u itself: V = solve(u) is then bit-identical to the saved run's
        self.opt["u"] = jit_array(mi.Float, u) if u is not None else \
            self.steps.to_differential(self.params[self.key])
        self.albedo_key = self.envmap = None
        if self.cfg.albedo:
            suffixes = ("reflectance.data", "base_color.data") if self.texture else \
                ("reflectance.value", "base_color.value")
            keys = [k for k in self.params.keys() if k.startswith(f"{self.cfg.object}.bsdf.") and k.endswith(suffixes)]
            if not keys:
                raise PsdrError(f"{exp.file}: optimize.albedo: the object's BSDF has no constant "
                                f"reflectance/base_color to optimise (give 'texture: [W, H]' for a bitmap)")
            self.albedo_key = keys[0]
            if self.texture:  # the scene holds the initial texture already
                self.opt["albedo"] = self.albedo_value(self.texture_image())
            else:
                init = state_values.get("albedo")
                if init is None:
                    init = self.cfg.albedo_init or np.asarray(self.params[self.albedo_key]).ravel()
                self.opt["albedo"] = self.albedo_value(init)
            self.opt.set_learning_rate({"albedo": self.cfg.albedo_learning_rate})
        if self.cfg.envmap_rotation:
            self.envmap = Parameter(self.scene, ParameterConfig(kind="envmap_rotate", axis=self.cfg.envmap_axis), self.params)
            init = state_values.get("envmap_angle")
            self.opt["envmap_angle"] = mi.Float(float(init[0]) if init is not None
                                                else math.radians(self.cfg.envmap_init_deg))
            self.opt.set_learning_rate({"envmap_angle": self.cfg.envmap_learning_rate})

    def apply(self):
        """Write the optimiser's variables into the scene (AD-attached)."""
        self.params[self.key] = self.steps.from_differential(self.opt["u"])
        if self.albedo_key:  # (re-assigning opt["albedo"] would reset its Adam moments)
            self.params[self.albedo_key] = dr.clip(self.opt["albedo"], 0.0, 1.0)
        if self.envmap:
            self.envmap.apply(self.opt["envmap_angle"])  # calls params.update()
        else:
            self.params.update()

    def release(self):
        """Detach the scene from the optimiser's AD graph (nothing may linger in Dr.Jit's global
        AD state after a run, e.g. for later forward-mode work in the same process)."""
        with dr.suspend_grad():
            self.params[self.key] = dr.detach(self.params[self.key])
            if self.albedo_key:
                self.params[self.albedo_key] = dr.detach(self.params[self.albedo_key])
            for k in (self.envmap.keys if self.envmap else ()):
                self.params[k] = mi.AffineTransform4f(dr.detach(self.params[k].matrix))
            self.params.update()
        for k in list(self.opt.keys()):
            dr.disable_grad(self.opt[k])

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
        return out

    def export(self, iteration: int, seconds: float) -> State:
        adam = {k: adam_export(self.opt, k) for k in self.opt.keys()}
        return State(iteration, self.vertices(), self.F, adam, self.values(), seconds,
                     np.asarray(self.opt["u"], np.float32), self.basis, uv=self.uv)


def texture_experiment(exp, texture):
    """``exp`` with the optimised object's reflectance (diffuse) or base colour (principled)
    replaced by an in-memory bitmap holding ``texture`` (H, W, 3) (``optimize.albedo.texture``),
    looked up with the object's own bitmap's ``filter_type`` and ``wrap_mode`` if it has one."""
    if exp.scene.mitsuba is not None:
        raise PsdrError(f"{exp.file}: optimize.albedo.texture: not available for objects of a Mitsuba XML scene")
    obj = next(o for o in exp.scene.objects if o.name == exp.optimize.object)
    name = {"diffuse": "reflectance", "principled": "base_color"}.get(obj.bsdf.type)
    if name is None:
        raise PsdrError(f"{exp.file}: optimize.albedo.texture: the object's BSDF '{obj.bsdf.type}' has no "
                        f"reflectance or base_color (use diffuse or principled)")
    given = obj.bsdf.params.get(name)
    bitmap = BitmapConfig(data=np.asarray(texture, np.float32))
    if isinstance(given, BitmapConfig):  # the object's own lookup settings
        bitmap = replace(given, file=None, raw=False, data=bitmap.data)
    bsdf = BsdfConfig(obj.bsdf.type, {**obj.bsdf.params, name: bitmap})
    objects = [replace(o, bsdf=bsdf) if o.name == obj.name else o for o in exp.scene.objects]
    return replace(exp, scene=replace(exp.scene, objects=objects))


# --------------------------------------------------------------------------------------------
# Stages: what changes at each remesh (λ, image resolution)
# --------------------------------------------------------------------------------------------
def stage_at(cfg, iteration: int) -> int:
    """Remesh stage of the shape that ``iteration`` optimises: the number of entries a > 0 of
    ``remesh.at`` with a ≤ iteration (the remesh at a happens at the start of iteration a; stage 0
    is the initial shape)."""
    return sum(1 for a in cfg.remesh.at if 0 < a <= iteration)


def stage_value(values: tuple, stage: int):
    """The value of a per-stage key (``lambda``, ``downsample``) at ``stage``; a single value holds
    for every stage."""
    return values[min(stage, len(values) - 1)]


def stage_experiment(exp, stage: int):
    """``exp`` with the film of ``stage``: W/k × H/k pixels for ``downsample`` k."""
    k = stage_value(exp.optimize.downsample, stage)
    if k == 1:
        return exp
    return replace(exp, scene=replace(exp.scene, width=exp.scene.width // k, height=exp.scene.height // k))


def downsample(image: np.ndarray, k: int) -> np.ndarray:
    """Mean of every k × k block of pixels of an (H, W, C) image. With the box pixel filter every
    render uses, a pixel of the W/k × H/k film integrates exactly the area of its k² pixels at
    W × H, so this is the target a render at the lower resolution would estimate."""
    if k == 1:
        return image
    H, W, C = image.shape
    return image.reshape(H // k, k, W // k, k, C).mean(axis=(1, 3))


def adjoint_image(scene, view: int, spp: int, seed: int, iteration: int) -> mi.Float:
    """Primal render P of ``view`` (flat W·H·3, no AD) from samples of its own random stream, for
    the derivative of :func:`l1_loss`."""
    image = render_view(scene, view, spp, seed=pass_seed(seed, view, iteration, ADJOINT_STREAM))
    return jit_array(mi.Float, np.ravel(image))


def l1_loss(image: mi.Float, target: mi.Float, adjoint: mi.Float | None = None) -> mi.Float:
    """L = mean |I − T| with derivative ∂L = mean sign(I − T)·∂I.

    With ``adjoint`` P (an independent primal render of the same view) the value is mean |P − T|
    and the derivative mean sign(P − T)·∂I. Taking the sign from the AD image I itself (n
    samples) gives the exact gradient of E|I_n − T|, the L1 loss of a noisy render: a different
    objective, minimised where the median (not the mean) of the n-sample pixel estimate meets
    the target, whose gradient also shrinks wherever the residual is small next to the noise. A
    P of more samples, independent of those of ∂I, brings the estimate close to the gradient of
    the noise-free image's L1 loss at the cost of a forward render (docs/optimize.md, "Gradient
    quality per second")."""
    if adjoint is None:
        return dr.mean(dr.abs(image - target))
    sign = dr.sign(adjoint - target)
    return dr.mean(dr.abs(adjoint - target)) + dr.mean(sign * (image - dr.detach(image)))


def batch_views(seed: int, iteration: int, count: int, size: int) -> list:
    """The mini-batch of iteration ``iteration``: a function of (seed, iteration) only."""
    rng = np.random.default_rng([seed, iteration])
    return sorted(rng.choice(count, size=min(size, count), replace=False).tolist())


def learning_rate_at(cfg, iteration: int, total: int) -> float:
    """Adam's step at ``iteration`` of a ``total``-iteration run: ``learning_rate`` up to the last
    remesh s (the last of ``remesh.at`` before ``total``, else 0), then the geometric decay
    lr(i) = lr · (lr_final / lr)^((i − s) / (total − 1 − s)), reaching ``learning_rate_final``
    at the last iteration; constant when ``learning_rate_final`` is unset."""
    lr, final = cfg.learning_rate, cfg.learning_rate_final
    s = max([a for a in cfg.remesh.at if a < total] + [0])
    if final is None or iteration <= s or total - 1 <= s:
        return lr
    return lr * (final / lr) ** (min(iteration - s, total - 1 - s) / (total - 1 - s))


def strip(target, current, zoom: int = 3):
    """target | current | |difference| side by side, pixels enlarged ``zoom`` times, linear RGB."""
    gap = np.ones((target.shape[0], 2, 3))
    row = np.concatenate([target, gap, current, gap, np.abs(target - current)], axis=1)
    return np.repeat(np.repeat(row, zoom, axis=0), zoom, axis=1)


def optimize(exp, iterations: int | None = None, resume: bool = False, progress=None, warn=print) -> OptimizeResult:
    """Run (or continue) the optimisation of ``exp.optimize``; see the module docstring.

    ``progress``: optional object with ``start(total)``, ``advance(n, loss)``; ``warn``: one-line
    messages (NaN gradients, interruption)."""
    cfg = exp.optimize
    if cfg is None:
        raise PsdrError(f"{exp.file}: optimize: missing (expected at least {{object: NAME}})")
    total = cfg.iterations if iterations is None else iterations
    if total < 1:
        raise PsdrError(f"--iterations: expected a positive number, got {total}")
    backend.activate(exp)
    check_stages(exp)
    files = RunFiles(exp.run_dir)
    with lock_run(files), backend.optimization_threads():
        return _optimize(exp, files, total, iterations, resume, progress, warn)


def _optimize(exp, files: RunFiles, total: int, iterations, resume: bool, progress, warn) -> OptimizeResult:
    """:func:`optimize` once the run folder is locked."""
    cfg = exp.optimize
    state = State.load(files.state) if resume and files.state.exists() else None
    if resume and state is None:
        warn(f"--resume: no saved state in {files.root}; starting from the beginning")
    if state is not None and not same_experiment(files, exp):
        kept = move_aside(files)
        warn(f"--resume: {exp.file.name} changed since the run in {files.root} was saved; the old run is kept "
             f"in {kept}, starting from the beginning")
        state = None
    if state is not None and state.iteration > total:
        raise PsdrError(f"--iterations: {total} is fewer than the {state.iteration} iterations the run in "
                        f"{files.root} has done (ask for at least {state.iteration}, or start afresh without --resume)")
    # Targets and reference
    cameras = None
    if cfg.target_images:
        targets, cameras = image_targets(exp)
        reference = None
    else:
        reference = ground_truth(exp)
        write_mesh(files.reference, *reference)  # the shape this run's targets come from
        targets = render_targets(exp, files, reference)
    n_views = len(targets)
    bad = [v for v in cfg.preview_views if v >= n_views]
    if bad:
        raise PsdrError(f"{exp.file}: optimize.preview_views: view {bad[0]} does not exist (0..{n_views - 1})")
    # Shape
    if state is None:
        clear_run(files)  # a fresh run must never be confused with (or resumed as) an older one
        V, F, uv = initial_shape_uv(exp, reference)
        if cfg.remesh.method != "none":
            V, F = remesh(V, F, cfg.remesh.initial, cfg.remesh.method, warn=warn)
            uv = None  # (optimize.albedo.texture refuses remeshing: config.parse_optimize)
        start, values, seconds_so_far = 0, {}, 0.0
        write_mesh(files.checkpoint(0), V, F)
    else:
        V, F, start, values, seconds_so_far = state.V, state.F, state.iteration, state.values, state.seconds
        uv = state.uv
    fileio.write_json(files.run, run_record(exp))  # a fresh run, or the resumed one in the current version
    result = OptimizeResult(files.root, resumed_from=start)
    # the shape of iteration `start` before its remesh, if one is due: the stage of start − 1
    problem = Problem(exp, V, F, cameras, values, *((state.u, state.basis) if state is not None else (None, None)), uv=uv,
                      stage=stage_at(cfg, max(start - 1, 0)))
    if state is not None:
        for k, saved in state.adam.items():
            if k in problem.opt.keys():
                adam_import(problem.opt, k, saved)
    rows = read_log(files.log, start)
    write_log(files.log, rows)
    settings = Settings.from_experiment(exp)
    terms = exp.estimator.terms
    engine = Engine(settings, terms)
    if not engine.needs_edges:
        settings = settings.with_estimator(guiding="none")  # Mitsuba's integrators have their own
    stage_targets, target_arrays = stage_images(targets, problem.factor)
    if progress:
        progress.start(total, start)
    guides = guide_snapshot = None
    guided = uses_guides(settings, terms, pixel_count(problem))
    if state is not None and state.guide_V is not None and guided:
        # the guides in use when the run stopped, rebuilt from the shape they were built from
        guide_snapshot = (state.guide_V, state.guide_values)
        guides = rebuild_guides(problem, exp, settings, state.guide_V, state.guide_values, n_views, terms)
    it = start
    try:
        for it in range(start, total):
            if cfg.seconds is not None and seconds_so_far >= cfg.seconds:
                total = it  # the time budget is spent (a resumed run that had finished)
                break
            t_start = time.perf_counter()
            if it in cfg.remesh.at and it > 0:
                k = cfg.remesh.at.index(it)
                V2, F2 = remesh(problem.vertices(), problem.F, cfg.remesh.vertices[k], cfg.remesh.method
                                if cfg.remesh.method != "none" else "isotropic",
                                warn=lambda m: warn(f"iteration {it}: {m}"))
                problem.release()
                factor = problem.factor
                problem = Problem(exp, V2, F2, cameras, problem.values(), stage=stage_at(cfg, it))
                if problem.factor != factor:
                    stage_targets, target_arrays = stage_images(targets, problem.factor)
                    guided = uses_guides(settings, terms, pixel_count(problem))
                guides = None
            problem.apply()
            problem.scene.objects[cfg.object].vertices = problem.vertices()
            problem.scene.objects[cfg.object].faces = problem.F
            edges = edge_list(problem.scene, exp.estimator, settings.edge_sort) if engine.needs_edges else None
            t_guide = time.perf_counter()
            anchor = max([a for a in cfg.remesh.at if a <= it] + [0])  # guides restart after a remesh
            if guided and (guides is None or (it - anchor) % cfg.guide_every == 0):
                with dr.suspend_grad():
                    guides = make_guides(problem.scene, edges, list(range(n_views)), terms, settings)
                guide_snapshot = (problem.vertices(), problem.values())
            t_render = time.perf_counter()
            views = batch_views(exp.seed, it, n_views, cfg.batch_size)
            loss = mi.Float(0.0)
            for v in views:
                img = engine.image(problem, edges, v, it, guides)
                adjoint = adjoint_image(problem.scene, v, cfg.adjoint_spp, exp.seed, it) if cfg.adjoint_spp else None
                loss += l1_loss(img, target_arrays[v], adjoint) / len(views)
            dr.backward(loss)
            loss_value = float(loss[0])
            t_post = time.perf_counter()
            grads = [np.asarray(dr.grad(problem.opt[k])) for k in problem.opt.keys()]
            skipped = not all(np.isfinite(g).all() for g in grads) or not math.isfinite(loss_value)
            if skipped:
                warn(f"iteration {it}: non-finite gradient or loss; update skipped")
                result.skipped += 1
                for k in problem.opt.keys():
                    dr.set_grad(problem.opt[k], 0.0)
            else:
                if cfg.learning_rate_final is not None:
                    problem.opt.set_learning_rate(learning_rate_at(cfg, it, total))
                problem.opt.step()
            t_end = time.perf_counter()
            seconds_so_far += t_end - t_start
            row = {"iteration": it, "loss": f"{loss_value:.6g}", "vertices": len(problem.vertices()),
                   "seconds_guiding": f"{t_render - t_guide:.4f}", "seconds_rendering": f"{t_post - t_render:.4f}",
                   "seconds_post": f"{(t_guide - t_start) + (t_end - t_post):.4f}",
                   "seconds_total": f"{seconds_so_far:.3f}", "skipped": int(skipped),
                   "guide_bytes": sum(g.stats.memory_bytes for _, g in guides.all()) if guides else 0}
            rows.append(row)
            result.losses.append(loss_value)
            # Persist: the log row, the checkpoint when due, then the state after this iteration
            # (a kill before the state is saved repeats this iteration on --resume: its log row is
            # dropped and its checkpoint rewritten, so nothing saved is ever missing)
            append_log(files.log, row)
            problem.apply()
            if cfg.seconds is not None and seconds_so_far >= cfg.seconds:
                total = it + 1  # time budget spent: this is the last iteration
            if (it + 1) % cfg.checkpoint_every == 0 or it + 1 == total:
                result.checkpoints.append(save_checkpoint(problem, files, it + 1, stage_targets, exp))
            saved = problem.export(it + 1, seconds_so_far)
            if guide_snapshot is not None:
                saved.guide_V, saved.guide_values = guide_snapshot
            saved.save(files.state)
            if progress:
                progress.advance(1, loss_value)
            if it + 1 == total:
                break
        it = total
    except KeyboardInterrupt:
        result.interrupted = True
        warn(f"interrupted during iteration {it}: {it} completed iterations are saved in {files.state}; "
             f"continue with --resume")
        return result
    finally:
        problem.release()  # nothing of this run may linger in Dr.Jit's global AD graph
    result.iterations, result.seconds = total, seconds_so_far
    result.budget_stop = cfg.seconds is not None and total < (iterations or cfg.iterations)
    if cfg.seconds is not None and cfg.remesh.at and total < max(cfg.remesh.at) and total < (iterations or cfg.iterations):
        warn(f"the time budget ({cfg.seconds:g} s) ended the run at iteration {total}, before the remesh at "
             f"iteration {max(cfg.remesh.at)}: the final mesh has {len(problem.vertices())} vertices")
    write_mesh(files.final, problem.vertices(), problem.F)
    result.final = files.final
    plot_loss(files, read_log(files.log, total))
    fileio.write_json(files.summary, {
        "experiment": str(exp.file), "iterations": total, "resumed_from": start, "views": n_views,
        "final": str(files.final), "final_vertices": int(len(problem.vertices())),
        "values": {k: (str(files.albedo) if k == "albedo" and problem.texture else v.tolist())
                   for k, v in problem.values().items()}, "skipped_updates": result.skipped,
        "seconds": seconds_so_far})
    return result


def optimize_variants(exp: Experiment, labels=None, iterations: int | None = None, resume: bool = False,
                      progress=None, warn=print):
    """Run every run of ``exp`` (its ``optimize.variants``, or those in ``labels``; the experiment
    itself without variants) one after another; yields (label, OptimizeResult) as each ends.

    ``progress(label)``: optional context manager factory giving each run's progress object."""
    if exp.optimize is None:
        raise PsdrError(f"{exp.file}: optimize: missing (expected at least {{object: NAME}})")
    for label, run in variant_experiments(exp, labels):
        if progress is None:
            yield label, optimize(run, iterations=iterations, resume=resume, warn=warn)
            continue
        with progress(label) as bar:
            result = optimize(run, iterations=iterations, resume=resume, progress=bar, warn=warn)
        yield label, result


def rebuild_guides(problem, exp, settings, V, values: dict, n_views: int, terms):
    """The guides of ``problem`` as they were built from vertices ``V`` and unknowns ``values``
    (a resumed run continues with the guides the interrupted run was using; guide building is
    seeded, so they are the same guides). The scene is left for :meth:`Problem.apply` to reset."""
    cfg = exp.optimize
    with dr.suspend_grad():
        problem.params[problem.key] = jit_array(mi.Float, np.ravel(V))
        if problem.albedo_key and "albedo" in values:
            problem.params[problem.albedo_key] = problem.albedo_value(values["albedo"])
        if problem.envmap and "envmap_angle" in values:
            problem.envmap.apply(mi.Float(float(np.ravel(values["envmap_angle"])[0])))
        else:
            problem.params.update()
        problem.scene.objects[cfg.object].vertices = np.asarray(V, np.float64)
        problem.scene.objects[cfg.object].faces = problem.F
        edges = edge_list(problem.scene, exp.estimator, settings.edge_sort)
        return make_guides(problem.scene, edges, list(range(n_views)), terms, settings)


def pixel_count(problem) -> int:
    """Pixels of the film the current stage renders (what ``guiding: auto`` decides by)."""
    width, height = problem.scene.resolution
    return width * height


def stage_images(targets, k: int):
    """The targets at downsampling factor ``k``: (H/k, W/k, 3) arrays and flat ``mi.Float`` copies."""
    images = [downsample(t, k) for t in targets]
    return images, [jit_array(mi.Float, np.ravel(t)) for t in images]


def save_checkpoint(problem, files: RunFiles, iteration: int, targets, exp) -> Path:
    """iter_NNNN.ply and a target | current | |difference| strip per preview view, at the
    stage's resolution (``targets``: the stage's) with pixels enlarged to the film's size."""
    path = files.checkpoint(iteration)
    write_mesh(path, problem.vertices(), problem.F)
    if problem.texture:  # the recovered texture: albedo.exr (linear) and albedo.png, per checkpoint a preview
        texture = problem.texture_image()
        fileio.write_rgb_exr(files.albedo, texture, {"psdr.iteration": str(iteration)})
        fileio.write_preview(files.albedo.with_suffix(".png"), texture)
        fileio.write_preview(files.previews / f"iter_{iteration:04d}_albedo.png", texture)
    k = problem.factor
    with dr.suspend_grad():
        for v in exp.optimize.preview_views:
            current = render_view(problem.scene, v, 16, seed=exp.seed)
            full = [np.repeat(np.repeat(image, k, axis=0), k, axis=1) for image in (targets[v], current)]
            fileio.write_preview(files.previews / f"iter_{iteration:04d}_view_{v:03d}.png", strip(*full))
    return path


def plot_loss(files: RunFiles, rows: list):
    if not rows:
        return
    it = np.array([int(r["iteration"]) for r in rows])
    loss = np.array([float(r["loss"]) for r in rows])
    plots.lines(files.root / "loss.png", {"L1 loss": (it, loss)}, "iteration", "image L1 loss",
                "psdr optimize", logy=True)
