"""``optimize.cameras.focal``: the focal length refined with the poses, one scale per camera model.

Views with identical intrinsics (field of view, principal point; one film size per scene) share
a camera model g and one unknown x_g = log s_g: view v's focal length becomes f_v' = e^(x_g) f_v,
its principal point kept, i.e. its horizontal field of view 2 atan(tan(φ_v/2) e^(−x_g)). The value
is written into the sensor's ``x_fov`` and the derivative rides in the factor σ_v = e^(x_g − detach
x_g) that the sensor carries while the corrections are attached (:mod:`psdr_cli.estimators.focal`:
the interior term's rays, the primary term's projection and the direct term's pixel-tied camera
ray all differentiate it).

Gauge: a similarity of the whole capture (cameras and object together) does not change a focal
length, so the focal scale adds no gauge direction (the poses' projection,
:mod:`.camera_refinement`, leaves x alone). It is nearly ambiguous with a move along the optical
axis when the object is shallow against its distance (both scale its image about the principal
point; only the perspective differs), and so with the object's size once the cameras' mean
distance is pinned: a focal scale k and the object scaled by k give the same image size f·size/d
at every distance d, and only the perspective (the object's depth against d) tells them apart, so
such a run needs views close to the object (docs/benchmarks/focal_refinement.md); the
translation's own runaway bound keeps the pair from drifting far.

Schedule and stops: the poses' (start, warm-up, fall), at the rate ``focal_learning_rate``; a
model whose gradient is not finite or whose |x_g| passes log(1 + ``max_focal``) stops (one line
naming its views) and goes back to its value before that step.
"""
from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi
import numpy as np

from ..config.scene_ids import sensor_id
from ..errors import PsdrError
from ..scene.sensors import attach as attach_focal, is_perspective, scaled_fov
from ..support.jitarray import jit_array


def camera_models(params, views: int) -> np.ndarray:
    """The camera model of each view (views,): views with the same field of view and principal
    point share one, numbered in order of first appearance."""
    keys = {}
    out = []
    for v in range(views):
        row = tuple(round(float(dr.ravel(params[f"{sensor_id(v)}.{k}"])[0]), 9) if f"{sensor_id(v)}.{k}" in params
                    else 0.0 for k in ("x_fov", "principal_point_offset_x", "principal_point_offset_y"))
        out.append(keys.setdefault(row, len(keys)))
    return np.asarray(out, np.int64)


class FocalCorrections:
    """x_g = log s_g of every camera model: an entry ``focal`` of the poses' Adam optimiser
    ``opt``, the fields of view and focal factors they give each sensor, and the stopped models."""

    def __init__(self, cfg, params, views: int, values: dict, opt):
        self.cfg, self.opt = cfg, opt
        self.keys = [f"{sensor_id(v)}.x_fov" for v in range(views)]
        self.sensors = [params.properties[k][2] for k in self.keys] if all(k in params for k in self.keys) else []
        if len(self.sensors) != views or not all(is_perspective(s) for s in self.sensors):
            raise PsdrError("optimize.cameras.focal: every training view needs a perspective camera")
        self.fov0 = np.array([float(dr.ravel(params[k])[0]) for k in self.keys])
        self.model = camera_models(params, views)
        saved = values.get("camera_focal")
        self.opt["focal"] = jit_array(mi.Float, np.zeros(self.models) if saved is None else np.ravel(saved))
        stopped = values.get("camera_focal_stopped")
        self.stopped = np.zeros(self.models, bool) if stopped is None else np.asarray(stopped).ravel() > 0.5

    @property
    def models(self) -> int:
        return int(self.model.max()) + 1

    def logs(self, values: dict | None = None) -> np.ndarray:
        """x per model (no AD), of the saved ``values`` when given."""
        if values is not None and "camera_focal" in values:
            return np.ravel(values["camera_focal"]).astype(np.float64)
        return np.asarray(self.opt["focal"], np.float64)

    def scales(self, values: dict | None = None) -> np.ndarray:
        """s_v = e^(x_g) of every view (views,)."""
        return np.exp(self.logs(values))[self.model]

    def write(self, params, attached: bool, values: dict | None = None):
        """Every view's field of view (the value) and, while ``attached``, its focal factor σ_v."""
        for key, fov in self.fields_of_view(values).items():
            params[key] = fov
        self.attach(attached, values)

    def fields_of_view(self, values: dict | None = None) -> dict:
        """{sensor ``x_fov`` key: 2 atan(tan(φ_v/2) / s_v)} (of the saved ``values`` when given)."""
        return {key: scaled_fov(fov0, float(s)) for key, fov0, s in zip(self.keys, self.fov0, self.scales(values))}

    def attach(self, attached: bool, values: dict | None = None):
        """Let every view's sensor carry its focal factor σ_v while ``attached`` (none otherwise)."""
        x = self.opt["focal"]
        sigma = dr.exp(x - dr.detach(x)) if attached and values is None else None
        for v, sensor in enumerate(self.sensors):
            attach_focal(sensor, None if sigma is None else dr.gather(mi.Float, sigma, int(self.model[v])))

    def set_gradient(self, iteration: int, warn) -> None:
        """The gradient Adam steps with: zero for stopped models; a non-finite one stops its model."""
        g = np.asarray(dr.grad(self.opt["focal"]), np.float64)
        for m in np.flatnonzero(~np.isfinite(g) & ~self.stopped):
            warn(f"iteration {iteration}: {self.describe(m)}: non-finite focal gradient; its focal refinement stops")
            self.stopped[m] = True
        dr.set_grad(self.opt["focal"], jit_array(mi.Float, np.where(self.stopped, 0.0, np.nan_to_num(g))))

    def settle(self, before: np.ndarray, iteration: int, warn) -> None:
        """After Adam's step: a model beyond the bound stops; stopped models keep ``before``."""
        after = self.logs()
        limit = math.log1p(self.cfg.max_focal)
        for m in np.flatnonzero(~(np.abs(np.nan_to_num(after, nan=np.inf)) <= limit) & ~self.stopped):
            warn(f"iteration {iteration}: {self.describe(m)}: focal correction beyond {100 * self.cfg.max_focal:g} %; "
                 f"its focal refinement stops")
            self.stopped[m] = True
        self.opt["focal"] = jit_array(mi.Float, np.where(self.stopped, before, after))

    def describe(self, m: int) -> str:
        views = np.flatnonzero(self.model == m)
        return f"camera{'s' if len(views) > 1 else ''} {', '.join(str(v) for v in views)}"

    def detach(self, params) -> None:
        """The fields of view without focal factors (the end of a run)."""
        self.write(params, attached=False)

    def values(self) -> dict:
        return {"camera_focal": self.logs(), "camera_focal_stopped": self.stopped.astype(np.float64)}
