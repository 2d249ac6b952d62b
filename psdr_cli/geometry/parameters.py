"""The scalar scene parameter θ of ``psdr grad`` (YAML ``parameter:``), applied differentiably.

With c the centre of the object's bounding box at θ = 0 and a the (unit) axis:

- ``translate``: V(θ) = V0 + θ a                                  (θ in scene units)
- ``rotate``:    V(θ) = c + R(a, θ)(V0 − c)                       (θ in radians, right-handed)
- ``scale``:     V(θ) = c + (1 + θ a) ⊙ (V0 − c)                  (a per-axis rates, not normalised)
- ``envmap_rotate``: to_world(θ) = R(a, θ) · to_world(0) of every environment emitter.
- a camera (``camera: i``): ``translate``: to_world(θ) = T(θ a) · to_world(0); ``rotate``:
  to_world(θ) = T(o) R(a, θ) T(−o) · to_world(0) about the camera's own origin o.
- a camera's ``focal`` length: s = e^θ (θ = log s, dimensionless), f'(θ) = s·f, principal point
  kept: the sensor's field of view becomes 2 atan(tan(φ0/2) / e^θ) (its value, which finite
  differences render through Mitsuba's own camera) and the sensor carries the factor
  σ = e^(θ − detach θ) (value 1) whose derivative psdr's camera paths take
  (:mod:`psdr_cli.scene.sensors`, applied by :mod:`psdr_cli.estimators.focal`).

R(a, θ) v = v cosθ + (a × v) sinθ + a (a·v)(1 − cosθ) (Rodrigues).
"""
from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi
import numpy as np

from ..config.parameter import ParameterConfig
from ..config.scene_ids import INTERNAL_PREFIX, sensor_id
from ..errors import PsdrError
from ..scene.sensors import attach as attach_focal, is_perspective, scaled_fov


def rodrigues(axis, theta, v):
    """R(axis, θ) v for unit ``axis``."""
    a = mi.Vector3f(*(float(x) for x in axis))
    c, s = dr.cos(theta), dr.sin(theta)
    return v * c + dr.cross(a, v) * s + a * dr.dot(a, v) * (1.0 - c)


class Parameter:
    """θ ↦ scene parameters. ``apply(θ)`` writes them (θ may carry AD), ``reset()`` restores θ = 0."""

    def __init__(self, scene, config: ParameterConfig, params=None):
        self.config = config
        self.params = params if params is not None else mi.traverse(scene.mi_scene)
        if config.camera is not None:
            key = f"{sensor_id(config.camera)}.to_world"
            if key not in self.params:
                raise PsdrError(f"parameter.camera: no camera {config.camera} in the scene")
            self.keys = [key]
            self.initial = {key: mi.AffineTransform4f(self.params[key])}
            if config.kind == "focal":
                self.init_focal(scene, config.camera)
        elif config.kind == "envmap_rotate":
            prefix = f"{INTERNAL_PREFIX}emitter_"
            self.keys = [k for k in self.params.keys() if k.startswith(prefix) and k.endswith(".to_world")]
            if not self.keys:
                raise PsdrError("parameter: kind 'envmap_rotate' needs an envmap or sky emitter in the scene")
            self.initial = {k: mi.AffineTransform4f(self.params[k]) for k in self.keys}
        else:
            key = f"{config.object}.vertex_positions"
            if key not in self.params:
                raise PsdrError(f"parameter.object: no object named '{config.object}' in the scene")
            self.keys = [key]
            V0 = np.asarray(self.params[key], np.float64).reshape(-1, 3)
            self.initial = {key: mi.Float(self.params[key])}
            self.center = mi.Point3f(*(float(x) for x in (V0.min(0) + V0.max(0)) / 2))

    def init_focal(self, scene, camera: int):
        """The camera's field of view at θ = 0 (its ``x_fov`` key, a perspective camera's only)."""
        self.sensor = scene.mi_scene.sensors()[camera]
        if not is_perspective(self.sensor):
            raise PsdrError(f"parameter.camera: camera {camera} is not a perspective camera; kind 'focal' scales a "
                            f"perspective camera's focal length")
        self.keys = [f"{sensor_id(camera)}.x_fov"]
        self.initial = {self.keys[0]: float(dr.ravel(self.params[self.keys[0]])[0])}

    @property
    def name(self) -> str:
        c = self.config
        if c.kind == "focal":
            return f"focal camera {c.camera} (log scale)"
        what = "environment" if c.kind == "envmap_rotate" else \
            (f"camera {c.camera}" if c.camera is not None else c.object)
        return f"{c.kind} {what} axis ({', '.join(f'{a:g}' for a in c.axis)})"

    def vertices(self, theta):
        """V(θ) of the object as a flat AD buffer."""
        c, a = self.config, self.config.axis
        V0 = dr.unravel(mi.Point3f, self.initial[self.keys[0]])
        if c.kind == "translate":
            V = V0 + theta * mi.Vector3f(*a)
        elif c.kind == "rotate":
            V = self.center + rodrigues(a, theta, V0 - self.center)
        else:
            V = self.center + (1.0 + theta * mi.Vector3f(*a)) * (V0 - self.center)
        return dr.ravel(V)

    def camera_to_world(self, theta):
        """to_world(θ) of the moving camera (see the module docstring)."""
        T0 = self.initial[self.keys[0]]
        a = list(self.config.axis)
        if self.config.kind == "translate":
            return mi.AffineTransform4f().translate(mi.Vector3f(*a) * theta) @ T0
        o = T0.translation()
        rot = mi.AffineTransform4f().rotate(a, theta * (180.0 / math.pi))
        return mi.AffineTransform4f().translate(o) @ rot @ mi.AffineTransform4f().translate(-o) @ T0

    @property
    def moves_camera(self) -> bool:
        """Whether θ moves a camera (``parameter.camera``)."""
        return self.config.camera is not None

    def apply_focal(self, theta: mi.Float):
        """The focal scale e^θ: its value into the sensor's field of view, its derivative into
        the factor the sensor carries (none when θ carries no derivative; module docstring)."""
        value = float(dr.ravel(dr.detach(theta))[0])
        self.params[self.keys[0]] = scaled_fov(self.initial[self.keys[0]], math.exp(value))
        attach_focal(self.sensor, dr.exp(theta - value) if dr.grad_enabled(theta) else None)

    def apply(self, theta):
        theta = mi.Float(theta)
        if self.config.kind == "focal":
            self.apply_focal(theta)
        elif self.config.camera is not None:
            self.params[self.keys[0]] = self.camera_to_world(theta)
        elif self.config.kind == "envmap_rotate":
            rot = mi.Transform4f().rotate(list(self.config.axis), theta * (180.0 / math.pi))
            for k in self.keys:
                self.params[k] = mi.AffineTransform4f(rot.matrix) @ self.initial[k]
        else:
            self.params[self.keys[0]] = self.vertices(theta)
        self.params.update()

    def reset(self):
        self.apply(mi.Float(0.0))
