"""``optimize.cameras``: the training views' poses refined with the shape.

View v's camera-to-world transform (Mitsuba's, 4×4) becomes

    M_v(r_v, τ_v) = T(o_v + d_v Q_v τ_v) · R(Q_v r_v) · T(−o_v) · M_v⁰,

a rotation R(ρ) = exp([ρ]×) (Rodrigues, radians) about the camera's centre o_v (tilt, pan and
roll), then a translation (sideways, and along the optical axis), both in the camera's own axes
Q_v (the rotation of M_v⁰), the translation in units of d_v, the view's distance from the
cameras' common look-at point c: both unknowns are angles of about the same size for the
image. Adam updates x = (r_v, τ_v) of every view per element; a view's moments wait while it is
out of the batch (masked updates). The gradients are psdr's camera derivatives (the interior
term's moving rays, the primary term's moving silhouettes, the direct term's sliding shadow
edges: :mod:`psdr_cli.rendering.camera_motion`). Why the pivot is the camera's centre and not c:
docs/optimize.md, "Camera poses".

Gauge: a similarity of the whole capture (every camera and the object together) leaves the
images unchanged. To first order it moves x along seven directions: rotation about c by e_i
(r_v = Q_vᵀ e_i, τ_v = Q_vᵀ (e_i × (o_v − c)) / d_v), translation e_i (τ_v = Q_vᵀ e_i / d_v)
and scale about c (τ_v = Q_vᵀ (o_v − c) / d_v). After every step x is projected onto the complement of their
span G, x ← x − G (GᵀG)⁻¹ Gᵀ x, over the views still refined: the cameras keep their mean pose,
and the object stays in the dataset's frame and scale (comparable with a ground truth as is).

Schedule: nothing moves before iteration ``start`` (default: a fifth of the run, when the shape
has settled); the step then ramps linearly over ``warmup`` iterations to ``learning_rate``. A
view whose gradient is not finite, or whose correction leaves ``max_rotation_deg`` or
``max_translation``, stops: its correction goes back to its value before that step and stays.

``focal: true`` adds a focal scale per camera model (:mod:`.focal_refinement`), an entry of the
same Adam optimiser with its own rate and bound; it adds no gauge direction.
"""
from __future__ import annotations

import math
from dataclasses import replace

import drjit as dr
import mitsuba as mi
import numpy as np

from ..config.scene_ids import sensor_id
from ..errors import PsdrError
from ..experiment.dataset_frame import look_at_point
from ..support.jitarray import jit_array
from .focal_refinement import FocalCorrections

#: The unknowns' names (Adam entries, and ``camera_<name>`` in a run's saved values).
PARTS = ("rotation", "translation")

#: Mitsuba's camera axes (x left, y up, z forward) from OpenCV's (x right, y down, z forward).
OPENCV_FLIP = np.diag([-1.0, -1.0, 1.0, 1.0])


def refines_cameras(cfg, views: int, dataset: bool, engine: str, where) -> bool:
    """Whether ``optimize.cameras`` (``cfg``) refines the poses of a run with ``views`` training
    views: ``on``, or ``auto`` with a camera dataset; a single view (its pose is the gauge) or
    Mitsuba's engine (its camera derivatives are not psdr's) refuse ``on`` in one line."""
    if cfg.mode == "off" or (cfg.mode == "auto" and (not dataset or views < 2 or engine != "psdr")):
        return False
    if views < 2:
        raise PsdrError(f"{where}: optimize.cameras: a run with one view cannot refine its pose (a single camera's "
                        f"pose is not observable apart from the object's); set cameras: off")
    if engine != "psdr":
        raise PsdrError(f"{where}: optimize.cameras: needs estimator.engine psdr (the camera derivatives are psdr's)")
    return True


def with_camera_mode(exp, views: int):
    """``exp`` with ``optimize.cameras.mode`` decided (``on`` or ``off``: :func:`refines_cameras`)
    for a run with ``views`` training views."""
    cfg = exp.optimize
    on = refines_cameras(cfg.cameras, views, cfg.target_dataset is not None, exp.estimator.engine, exp.file)
    cameras = replace(cfg.cameras, mode="on" if on else "off")
    return replace(exp, optimize=replace(cfg, cameras=cameras))


def rotation_matrices(r):
    """R(r) = I cos θ + sinc θ [r]× + (1 − cos θ)/θ² r rᵀ, θ = |r|, for a Vector3f ``r`` (AD:
    θ² is floored before its root, so the derivative at r = 0 is the exact [·]×)."""
    t2 = dr.squared_norm(r)
    theta = dr.sqrt(dr.maximum(t2, 1e-20))
    small = t2 < 1e-8
    a = dr.select(small, 1.0 - t2 / 6.0, dr.sin(theta) / theta)
    b = dr.select(small, 0.5 - t2 / 24.0, (1.0 - dr.cos(theta)) / dr.maximum(t2, 1e-20))
    c = 1.0 - b * t2
    x, y, z = r.x, r.y, r.z
    return mi.Matrix3f(c + b * x * x, b * x * y - a * z, b * x * z + a * y,
                       b * y * x + a * z, c + b * y * y, b * y * z - a * x,
                       b * z * x - a * y, b * z * y + a * x, c + b * z * z)


def camera_frames(to_world: np.ndarray) -> tuple:
    """(origins o_v, axes Q_v, look-at point c, distances d_v) of cameras whose (n, 4, 4)
    ``to_world`` transforms are in Mitsuba's axes: Q_v the rotation with unit columns, c the
    point closest to every optical axis (their mean centre when the axes are parallel),
    d_v = |o_v − c| (at least 1e-6)."""
    origins = to_world[:, :3, 3]
    axes = to_world[:, :3, :3] / np.linalg.norm(to_world[:, :3, :3], axis=1, keepdims=True)
    centre = look_at_point(origins, axes[:, :, 2])
    centre = origins.mean(0) if centre is None else centre
    return origins, axes, centre, np.maximum(np.linalg.norm(origins - centre, axis=1), 1e-6)


def gauge_basis(axes: np.ndarray, origins: np.ndarray, centre: np.ndarray, distances: np.ndarray, rotation: bool,
                translation: bool) -> np.ndarray:
    """G (n_unknowns × k): the first-order moves of the corrections (rotation block, then
    translation block, each view-major, in each camera's axes ``axes`` Q_v) under a similarity of
    the whole capture (module docstring): k = 7 with both parts, 4 with the translation alone, 0
    with the rotation alone (the centres stay: no similarity but the identity keeps them all)."""
    n = len(origins)
    if not translation:
        return np.zeros((3 * n, 0))
    local = lambda w: np.einsum("vji,vj->vi", axes, w)  # noqa: E731 - Q_vᵀ w_v
    rel = (origins - centre) / distances[:, None]
    zero = np.zeros((n, 3))
    columns = []
    for i in range(3):
        e = np.tile(np.eye(3)[i], (n, 1))
        if rotation:
            columns.append((local(e), local(np.cross(e, rel))))
        columns.append((zero, local(e / distances[:, None])))
    columns.append((zero, local(rel)))
    blocks = [np.concatenate(([rot.ravel()] if rotation else []) + ([tr.ravel()] if translation else []))
              for rot, tr in columns]
    return np.stack(blocks, axis=1)


def without_gauge(x: np.ndarray, G: np.ndarray, free: np.ndarray) -> np.ndarray:
    """x ← x − G (GᵀG)⁻¹ Gᵀ x over the rows ``free`` (the other rows are kept as they are)."""
    if G.shape[1] == 0 or not free.any():
        return x
    Gf = G[free]
    coef, *_ = np.linalg.lstsq(Gf, x[free], rcond=None)
    out = x.copy()
    out[free] = x[free] - Gf @ coef
    return out


class CameraCorrections:
    """The pose corrections of every training view: their Adam optimiser, the transforms they
    give each sensor, the schedule, the stopped views and the gauge (module docstring)."""

    def __init__(self, cfg, params, views: int, values: dict, gauge: bool = True):
        """``cfg``: ``optimize.cameras``; ``params``: the scene's (each view's ``to_world`` as
        built, the corrections' origin); ``values``: saved corrections (:meth:`values`) or {};
        ``gauge``: project the similarities out (off when the scene is fixed and each view is
        fitted to it alone)."""
        self.cfg = cfg
        self.keys = [f"{sensor_id(v)}.to_world" for v in range(views)]
        self.initial = np.stack([np.array(params[k].matrix, np.float64).reshape(4, 4) for k in self.keys])
        self.origins, self.axes, self.centre, self.distances = camera_frames(self.initial)
        self.parts = tuple(p for p in PARTS if getattr(cfg, p))
        # a view's gradient is zero when it is not in the batch: masked, its moments wait for it
        self.opt = mi.ad.Adam(lr=cfg.learning_rate, mask_updates=True)
        for part in self.parts:
            saved = values.get(f"camera_{part}")
            start = np.zeros(3 * views) if saved is None else np.ravel(saved)
            self.opt[part] = jit_array(mi.Float, start)
        stopped = values.get("camera_stopped")
        self.stopped = np.zeros(views, bool) if stopped is None else np.asarray(stopped).ravel() > 0.5
        self.G = gauge_basis(self.axes, self.origins, self.centre, self.distances, "rotation" in self.parts,
                             "translation" in self.parts) if gauge else np.zeros((3 * views * len(self.parts), 0))
        self.M0 = [mi.Matrix4f(m) for m in self.initial]
        self.focal = FocalCorrections(cfg, params, views, values, self.opt) if cfg.focal else None
        self.attached = False  # whether the transforms written carry the corrections' AD graph

    @property
    def views(self) -> int:
        return len(self.keys)

    @property
    def moved(self) -> bool:
        """Whether any correction is non-zero (the cameras are no longer the dataset's)."""
        return bool(np.any(self.array() != 0)) or (self.focal is not None and bool(np.any(self.focal.logs() != 0)))

    def start(self, total: int) -> int:
        """The first iteration refined: ``start``, or a fifth of a ``total``-iteration run."""
        return self.cfg.start if self.cfg.start is not None else total // 5

    def refining(self, iteration: int, total: int) -> bool:
        """Whether the poses move at ``iteration`` (the schedule has begun; a view is left)."""
        return iteration >= self.start(total) and not self.stopped.all()

    def learning_rate(self, iteration: int, total: int) -> float:
        """The step at ``iteration``: 0 before the start, a linear ramp over ``warmup`` iterations
        up to ``learning_rate``, then a linear fall to ``learning_rate_final`` at the run's last
        iteration (the last steps average the gradients' noise away)."""
        start = self.start(total)
        k = iteration - start
        if k < 0:
            return 0.0
        lr, final = self.cfg.learning_rate, self.cfg.learning_rate_final
        ramp = min(1.0, (k + 1) / (self.cfg.warmup + 1))
        top = start + self.cfg.warmup
        fall = 0.0 if iteration <= top or total - 1 <= top else (iteration - top) / (total - 1 - top)
        return ramp * (lr + (final - lr) * min(fall, 1.0))

    def part(self, name: str, values: dict | None = None):
        """The corrections ``name`` as a Vector3f over the views (zeros when not refined), from
        ``values`` (saved, :meth:`values`) when given."""
        if values is not None and f"camera_{name}" in values:
            return dr.unravel(mi.Vector3f, jit_array(mi.Float, np.ravel(values[f"camera_{name}"])))
        if name in self.parts:
            x = self.opt[name] if self.attached else dr.detach(self.opt[name])
            return dr.unravel(mi.Vector3f, x)
        return dr.zeros(mi.Vector3f, self.views)

    def transforms(self, values: dict | None = None) -> dict:
        """{sensor ``to_world`` key: M_v(r_v, τ_v)} (AD-attached while :attr:`attached`), of the
        saved corrections ``values`` when given (no AD)."""
        Q = mi.Matrix3f(*(jit_array(mi.Float, self.axes[:, i, j]) for i in range(3) for j in range(3)))
        R = rotation_matrices(Q @ self.part("rotation", values))
        o = mi.Vector3f(*(jit_array(mi.Float, self.origins[:, i]) for i in range(3)))
        d = jit_array(mi.Float, self.distances)
        p = o - R @ o + d * (Q @ self.part("translation", values))
        A = mi.Matrix4f(R[0, 0], R[0, 1], R[0, 2], p.x, R[1, 0], R[1, 1], R[1, 2], p.y,
                        R[2, 0], R[2, 1], R[2, 2], p.z, 0.0, 0.0, 0.0, 1.0)
        return {key: mi.AffineTransform4f(dr.gather(mi.Matrix4f, A, v) @ self.M0[v])
                for v, key in enumerate(self.keys)}

    def scene_values(self) -> dict:
        """{sensor parameter: value}: every view's transform (:meth:`transforms`) and, with
        ``focal``, its field of view; :meth:`attach_focal` follows once they are written."""
        out = self.transforms()
        if self.focal is not None:
            out.update(self.focal.fields_of_view())
        return out

    def attach_focal(self):
        """With ``focal``: the sensors carry their focal factors while :attr:`attached`."""
        if self.focal is not None:
            self.focal.attach(self.attached)

    def write(self, params, values: dict | None = None):
        """Write every view's transform into ``params`` (of the saved ``values`` when given; no
        ``params.update()``)."""
        for key, value in self.transforms(values).items():
            params[key] = value
        if self.focal is not None:
            self.focal.write(params, self.attached, values)

    def detach(self, params):
        """Write the transforms without AD (the end of a run)."""
        self.attached = False
        with dr.suspend_grad():
            self.write(params)

    def step(self, iteration: int, total: int, warn):
        """One Adam step at the schedule's rate, then the stops and the gauge (module docstring)."""
        before = self.array()
        grads = np.concatenate([np.asarray(dr.grad(self.opt[p]), np.float64).reshape(-1, 3) for p in self.parts], 1)
        bad = ~np.isfinite(grads).all(1) & ~self.stopped
        for v in np.flatnonzero(bad):
            warn(f"iteration {iteration}: camera {v}: non-finite pose gradient; its pose refinement stops")
        self.stopped |= bad
        for k, p in enumerate(self.parts):
            g = np.where(self.stopped[:, None], 0.0, np.nan_to_num(grads[:, 3 * k:3 * k + 3]))
            dr.set_grad(self.opt[p], jit_array(mi.Float, g.ravel()))
        focal_before = None
        if self.focal is not None:
            self.focal.set_gradient(iteration, warn)
            focal_before = self.focal.logs()
        self.opt.set_learning_rate(self.rates(iteration, total))
        self.opt.step()
        if self.focal is not None:
            self.focal.settle(focal_before, iteration, warn)
        after = self.array()
        runaway = self.beyond_bounds(after) & ~self.stopped
        for v in np.flatnonzero(runaway):
            warn(f"iteration {iteration}: camera {v}: pose correction beyond {self.cfg.max_rotation_deg:g}° or "
                 f"{self.cfg.max_translation:g} of its distance; its pose refinement stops")
        self.stopped |= runaway
        after[self.stopped] = before[self.stopped]
        free = np.repeat(~self.stopped, 3)
        x = np.concatenate([after[:, 3 * k:3 * k + 3].ravel() for k in range(len(self.parts))])
        x = without_gauge(x, self.G, np.tile(free, len(self.parts)))
        self.assign(x.reshape(len(self.parts), -1, 3))

    def rates(self, iteration: int, total: int) -> dict:
        """Each Adam entry's step: the schedule's, the focal scale's in proportion
        (``focal_learning_rate`` / ``learning_rate``)."""
        lr = self.learning_rate(iteration, total)
        out = {p: lr for p in self.parts}
        if self.focal is not None:
            out["focal"] = lr * self.cfg.focal_learning_rate / self.cfg.learning_rate
        return out

    def focal_scales(self, values: dict | None = None) -> np.ndarray:
        """The focal scale s_v of every view (ones without ``focal``)."""
        return np.ones(self.views) if self.focal is None else self.focal.scales(values)

    def array(self) -> np.ndarray:
        """(views, 3 · parts) the corrections, rotation first."""
        return np.concatenate([np.asarray(self.opt[p], np.float64).reshape(-1, 3) for p in self.parts], 1)

    def assign(self, parts: np.ndarray):
        """Set the corrections (parts × views × 3), Adam's moments kept."""
        for k, p in enumerate(self.parts):
            self.opt[p] = jit_array(mi.Float, parts[k].ravel())

    def beyond_bounds(self, x: np.ndarray) -> np.ndarray:
        """Views whose correction is not finite or leaves the bounds."""
        out = ~np.isfinite(x).all(1)
        for k, p in enumerate(self.parts):
            size = np.linalg.norm(np.nan_to_num(x[:, 3 * k:3 * k + 3], nan=np.inf), axis=1)
            limit = math.radians(self.cfg.max_rotation_deg) if p == "rotation" else self.cfg.max_translation
            out |= size > limit
        return out

    def values(self) -> dict:
        """``camera_<part>`` (views × 3) and ``camera_stopped`` (views,) for the saved state."""
        out = {f"camera_{p}": np.asarray(self.opt[p], np.float64).reshape(-1, 3) for p in self.parts}
        out["camera_stopped"] = self.stopped.astype(np.float64)
        if self.focal is not None:
            out.update(self.focal.values())
        return out

    def matrices(self) -> np.ndarray:
        """(views, 4, 4) the corrected camera-to-world transforms in Mitsuba's axes (no AD)."""
        with dr.suspend_grad():
            was, self.attached = self.attached, False
            out = np.stack([np.array(t.matrix, np.float64).reshape(4, 4) for t in self.transforms().values()])
            self.attached = was
        return out

    def errors(self) -> tuple:
        """(rotation in degrees, translation in camera distances) of each view's correction."""
        x = self.values()
        r = x.get("camera_rotation", np.zeros((self.views, 3)))
        t = x.get("camera_translation", np.zeros((self.views, 3)))
        return np.degrees(np.linalg.norm(r, axis=1)), np.linalg.norm(t, axis=1)
