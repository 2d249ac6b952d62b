"""``optimize.envmap_rotation``: the environment's rotation angle θ about ``axis`` (radians; Adam
entry and saved value ``envmap_angle``), written as to_world(θ) = R(axis, θ) · to_world(0) of every
environment emitter (:mod:`psdr_cli.geometry.parameters`, kind ``envmap_rotate``). Owns those
emitters' transforms; no checkpoint file (``psdr export`` rotates the experiment's map)."""
from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi
import numpy as np

from ...config.parameter import ParameterConfig
from ...geometry.parameters import Parameter
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


UNKNOWN = EnvironmentRotation
