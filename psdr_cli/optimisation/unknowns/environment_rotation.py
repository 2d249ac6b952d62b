"""``optimize.envmap_rotation``: the environment's rotation angle θ about ``axis`` (radians; Adam
entry and saved value ``envmap_angle``), written as to_world(θ) = R(axis, θ) · to_world(0) of every
environment emitter (:mod:`psdr_cli.geometry.parameters`, kind ``envmap_rotate``). Owns those
emitters' transforms; no checkpoint file; ``psdr export`` writes the experiment's map rotated by
θ (:func:`rotated_environment`)."""
from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi
import numpy as np

from ...config.parameter import ParameterConfig
from ...geometry.parameters import Parameter
from ...scene import meshes
from ...scene.build import environment_to_world, exr_texels
from .unknown import Saved, Start, Unknown


class EnvironmentRotation(Unknown):
    """The environment's rotation angle (module docstring)."""
    name = "environment_rotation"
    leaf_form = False

    @staticmethod
    def wanted(cfg) -> bool:
        return bool(cfg.envmap_rotation)

    def __init__(self, start: Start):
        super().__init__(start)
        cfg = start.cfg
        self.rotation = Parameter(start.scene, ParameterConfig(kind="envmap_rotate", axis=cfg.envmap_axis),
                                  start.params)
        init = start.values.get("envmap_angle")
        start.opt["envmap_angle"] = mi.Float(float(init[0]) if init is not None else math.radians(cfg.envmap_init_deg))
        start.opt.set_learning_rate({"envmap_angle": cfg.envmap_learning_rate})

    def entries(self) -> dict:
        return {"envmap_angle": (self.start.opt, "envmap_angle")}

    def transforms(self, theta) -> dict:
        """{emitter ``to_world``: R(axis, θ) · to_world(0)}."""
        rot = mi.Transform4f().rotate(list(self.rotation.config.axis), theta * (180.0 / math.pi))
        return {k: mi.AffineTransform4f(rot.matrix) @ self.rotation.initial[k] for k in self.rotation.keys}

    def scene_values(self) -> dict:
        return self.transforms(mi.Float(self.start.opt["envmap_angle"]))

    def write_saved(self, saved: Saved):
        if "envmap_angle" in saved.values:
            for k, value in self.transforms(mi.Float(float(np.ravel(saved.values["envmap_angle"])[0]))).items():
                self.start.params[k] = value

    def values(self) -> dict:
        return {"envmap_angle": np.asarray(self.start.opt["envmap_angle"], np.float64).ravel()}

    def summary(self, files) -> dict:
        return {"envmap_angle": self.values()["envmap_angle"].tolist()}

    def detach(self):
        for k in self.rotation.keys:
            self.start.params[k] = mi.AffineTransform4f(dr.detach(self.start.params[k].matrix))

    @staticmethod
    def export(asset, state, exp, where):
        """The angle in ``export.json``, and the experiment's environment map rotated by it
        (:func:`rotated_environment`)."""
        angle = state.values.get("envmap_angle")
        if angle is not None:
            asset.record["envmap_angle_deg"] = float(np.degrees(np.ravel(angle)[0]))
            asset.environment = rotated_environment(exp, float(np.ravel(angle)[0]), asset.notes)


def rotated_environment(exp, angle: float, notes: list):
    """The run's environment map rotated by ``angle`` (radians) about ``optimize.envmap_axis``, for
    the emitter's own ``rotate_deg`` (None, with a note, when the environment is no image file)."""
    emitters = [] if exp is None else [e for e in exp.scene.emitters if e.type in ("envmap", "sky")]
    if not emitters or emitters[0].type != "envmap" or exp.scene.mitsuba is not None:
        notes.append("the recovered environment rotation is not exported as an image (the environment is "
                     "not an envmap file of a YAML scene); it is in export.json")
        return None
    em = emitters[0]
    if em.file.suffix.lower() == ".exr":
        texels = exr_texels(em.file)
    else:
        texels = np.asarray(mi.Bitmap(str(em.file)).convert(component_format=mi.Struct.Type.Float32,
                                                             srgb_gamma=False))
    texels = np.asarray(texels, np.float64)[..., :3]
    if texels.shape[-1] == 1:
        texels = np.repeat(texels, 3, -1)
    M = np.array(environment_to_world(em.rotate_deg).matrix, np.float64)[:3, :3]
    R = meshes.rotation_matrix(exp.optimize.envmap_axis, np.degrees(angle))
    return rotate_latlong(texels, M.T @ R.T @ M)


def rotate_latlong(image, Q):
    """The lat-long map (Mitsuba's ``envmap`` parametrisation: u = atan2(x, −z)/2π, v = acos(y)/π
    of the local direction) E' with E'(l) = E(Q l), resampled bilinearly (u wraps, v clamps)."""
    H, W = image.shape[:2]
    v, u = (np.arange(H) + 0.5) / H, (np.arange(W) + 0.5) / W
    theta, phi = np.meshgrid(np.pi * v, 2 * np.pi * u, indexing="ij")
    l = np.stack([np.sin(theta) * np.sin(phi), np.cos(theta), -np.sin(theta) * np.cos(phi)], -1)
    d = l @ np.asarray(Q).T
    u2 = np.mod(np.arctan2(d[..., 0], -d[..., 2]) / (2 * np.pi), 1.0)
    v2 = np.arccos(np.clip(d[..., 1], -1, 1)) / np.pi
    x, y = u2 * W - 0.5, np.clip(v2 * H - 0.5, 0, H - 1)
    x0, y0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    fx, fy = (x - x0)[..., None], (y - y0)[..., None]
    xa, xb = np.mod(x0, W), np.mod(x0 + 1, W)
    ya, yb = y0, np.minimum(y0 + 1, H - 1)
    return ((1 - fy) * ((1 - fx) * image[ya, xa] + fx * image[ya, xb])
            + fy * ((1 - fx) * image[yb, xa] + fx * image[yb, xb]))


UNKNOWN = EnvironmentRotation
