"""Camera helpers shared by the boundary terms: film projection and camera connections.

Film coordinates are in pixels, q ∈ [0, W) × [0, H). For Mitsuba's perspective camera with a
horizontal field of view f, aspect a = W/H and principal point offset (o_x, o_y) (Mitsuba's
``principal_point_offset_x/y``, fractions of the film), a camera-space point (x, y, z) projects to

    q = ( W (½ − o_x − ½ x / (z tan(f/2))),  H (½ − o_y − ½ a y / (z tan(f/2))) )

(docs/theory.md §4): the principal point is the pixel (W (½ − o_x), H (½ − o_y)). The camera
connection W_e · f_s · |n·d0| of the direct and indirect terms is in §3.

A focal scale s (f' = s·f: tan(f/2) → tan(f/2)/s, :mod:`.focal`) that a sensor carries as an AD
factor σ reaches every camera path here: the camera rays are re-aimed (:func:`.focal.refocus`),
the projection divides tan(f/2) by σ, a camera connection's film position moves about the
principal point by σ (:func:`.focal.film_scale`) and its importance is multiplied by σ².

Parameters (experiment keys)
----------------------------
None: the film size, the field of view and the principal point come from the scene
(``scene.film``, ``scene.cameras[].fov``, ``scene.cameras[].principal_point``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from ..support.jitarray import jit_array
from ..scene.sensors import factor as focal_factor
from . import focal
from .shading_frame import bend_shading_normal


def camera_rays(sensor: mi.Sensor, sampler: mi.Sampler, width: int, height: int, spp: int):
    """One ray per (pixel, sample), pixel-major: lane i belongs to pixel i // spp, at the film
    point ((x, y) + ξ) / (W, H) with ξ uniform in [0,1)² (box filter)."""
    idx = dr.arange(mi.UInt32, width * height * spp)
    pixel = idx // dr.opaque(mi.UInt32, spp)
    pos = mi.Point2f(mi.Float(pixel % width), mi.Float(pixel // width)) + sampler.next_2d()
    film_uv = pos / mi.ScalarVector2f(width, height)
    ray, weight = sensor.sample_ray(0.0, sampler.next_1d(), film_uv, mi.Point2f(0.5))
    return focused(sensor, ray), weight


def focused(sensor: mi.Sensor, ray: mi.Ray3f) -> mi.Ray3f:
    """``ray`` of ``sensor`` re-aimed for the focal factor the sensor carries (:mod:`.focal`;
    the ray as it is without one). The box-filter weight is unchanged: the film integral is over
    film coordinates."""
    sigma = focal_factor(sensor)
    return ray if sigma is None else focal.refocus(sensor, ray, sigma)


def views_camera_rays(sensors, sampler: mi.Sampler, width: int, height: int, spp: int):
    """:func:`camera_rays` of several sensors in one wavefront: lane i belongs to view
    i // (W·H·spp) of ``sensors`` and, within it, to pixel (i mod W·H·spp) // spp at the film point
    ((x, y) + ξ) / (W, H); each distinct sensor's rays are computed on every lane and a lane keeps
    its own (a sensor listed several times, as for independent passes of one view, once)."""
    per_view = width * height * spp
    idx = dr.arange(mi.UInt32, per_view * len(sensors))
    view = idx // dr.opaque(mi.UInt32, per_view)
    pixel = (idx - view * dr.opaque(mi.UInt32, per_view)) // dr.opaque(mi.UInt32, spp)
    pos = mi.Point2f(mi.Float(pixel % width), mi.Float(pixel // width)) + sampler.next_2d()
    film_uv = pos / mi.ScalarVector2f(width, height)
    wavelength = sampler.next_1d()
    first, *others = sensor_groups(sensors)
    ray, weight = sensors[first[0]].sample_ray(0.0, wavelength, film_uv, mi.Point2f(0.5))
    ray = focused(sensors[first[0]], ray)
    for group in others:
        mine = view == group[0]
        for k in group[1:]:
            mine |= view == k
        ray_k, weight_k = sensors[group[0]].sample_ray(0.0, wavelength, film_uv, mi.Point2f(0.5), mine)
        ray_k = focused(sensors[group[0]], ray_k)
        ray, weight = dr.select(mine, ray_k, ray), dr.select(mine, weight_k, weight)
    return ray, weight


def sensor_groups(sensors) -> list:
    """The positions in ``sensors`` of each distinct sensor (by identity), in order of first appearance."""
    groups = {}
    for k, sensor in enumerate(sensors):
        groups.setdefault(id(sensor), []).append(k)
    return list(groups.values())


def principal_point_offset(sensor: mi.Sensor, params=None) -> tuple:
    """Mitsuba's (``principal_point_offset_x``, ``_y``) of a perspective sensor, as Python floats."""
    params = mi.traverse(sensor) if params is None else params
    return tuple(float(dr.ravel(params[f"principal_point_offset_{a}"])[0]) if f"principal_point_offset_{a}" in params
                 else 0.0 for a in "xy")


class Projection:
    """World → film (pixels) projection of one perspective sensor, differentiable in the point,
    the pose and the focal factor σ the sensor carries (module docstring: the principal point
    offset shifts the film centre ½ to ½ − o; tan(f/2) becomes tan(f/2)/σ)."""

    def __init__(self, sensor: mi.Sensor):
        params = mi.traverse(sensor)
        self.width, self.height = (int(s) for s in sensor.film().size())
        self.to_local = params["to_world"].inverse()
        self.origin = params["to_world"].translation()
        self.tan_half = math.tan(math.radians(float(dr.ravel(params["x_fov"])[0])) / 2)
        self.near = float(sensor.near_clip()) if hasattr(sensor, "near_clip") else 1e-2
        self.offset = principal_point_offset(sensor, params)
        # ½ − o as Python floats: exactly 0.5 for a centred camera (then its kernel has no offset in it)
        self.centre = (0.5 - self.offset[0], 0.5 - self.offset[1])
        self.sigma = focal_factor(sensor)  # the focal factor σ (AD, value 1) or None

    def __call__(self, p):
        """(film position in pixels, camera-space depth z) of world points ``p`` (any 3-vector
        type: a point, so that the camera's translation applies)."""
        local = self.to_local @ mi.Point3f(p)
        z = local.z
        aspect = self.width / self.height
        x = local.x / (z * self.tan_half)
        y = local.y / (z * self.tan_half)
        if self.sigma is not None:
            x, y = x * self.sigma, y * self.sigma
        cx, cy = self.centre
        return mi.Point2f(self.width * (cx - 0.5 * x), self.height * (cy - 0.5 * aspect * y)), z

    def project(self, p):
        """:meth:`__call__` (the name :class:`LaneCameras` gives it)."""
        return self(p)

    def importance(self, p):
        """Importance W_e of the pinhole toward world points ``p`` (no visibility, no film test):
        1 / (A cos³θ d²) with A = (2 tan(f/2))² / a the film's area at distance 1, θ the angle to
        the optical axis and d the distance, Mitsuba's ``PerspectiveCamera::importance``; ``p``
        any 3-vector type, taken as a point."""
        local = self.to_local @ mi.Point3f(p)
        dist2 = dr.squared_norm(local)
        cos = local.z * dr.rsqrt(dist2)
        area = (2 * self.tan_half) ** 2 * self.height / self.width
        if self.sigma is not None:
            area = area / (self.sigma * self.sigma)
        return dr.select(cos > 0, dr.rcp(area * cos * cos * cos * dist2), 0.0)


def film_pixel(uv, width: int):
    """Flat pixel index ⌊q_y⌋·W + ⌊q_x⌋ of a film position in pixels."""
    return mi.UInt32(dr.floor(uv.y)) * width + mi.UInt32(dr.floor(uv.x))


def camera_ray(sensor: mi.Sensor, uv, width: int, height: int, active=True):
    """The camera ray through film position ``uv`` (pixels): detached unless the camera moves
    (its pose, or the focal factor it carries: :func:`focused`)."""
    ray, _ = sensor.sample_ray(0.0, 0.5, uv / mi.ScalarVector2f(width, height), mi.Point2f(0.5), active)
    return focused(sensor, ray)


class SensorCamera:
    """One sensor seen as the boundary terms use a camera (W × H film, positions in pixels):
    ``camera(uv, active)`` is the camera ray through film position uv (:func:`camera_ray`) and
    ``camera.direction(x, active)`` Mitsuba's ``sample_direction`` towards points x, as
    (importance W_e, unit direction d0 from x to the camera, film position, valid, distance).
    With a principal point offset, W_e is :meth:`Projection.importance` (Mitsuba 3.9 zeroes its
    own outside the *centred* film rectangle, whatever the offset; inside the shifted film it
    has the same value: it depends on the angle and the distance only). With a focal factor σ
    (:mod:`.focal`) the film position moves about the principal point by σ and W_e is
    multiplied by σ² (values unchanged: σ = 1)."""

    def __init__(self, sensor: mi.Sensor, width: int, height: int):
        self.sensor, self.width, self.height = sensor, width, height

    def __call__(self, uv, active=True):
        return camera_ray(self.sensor, uv, self.width, self.height, active)

    def direction(self, x, active):
        it = dr.zeros(mi.Interaction3f)
        it.p = x
        ds, importance = self.sensor.sample_direction(it, mi.Point2f(0.5), active)
        uv, sigma = ds.uv, focal_factor(self.sensor)
        if any(principal_point_offset(self.sensor)):  # Projection's importance holds σ² already
            importance = mi.Spectrum(dr.select(ds.pdf > 0, Projection(self.sensor).importance(x), 0.0))
        elif sigma is not None:
            importance = importance * (sigma * sigma)
        if sigma is not None:
            cx, cy = Projection(self.sensor).centre
            uv = focal.film_scale(uv, (self.width * cx, self.height * cy), sigma)
        return importance, ds.d, uv, ds.pdf > 0, ds.dist


@dataclass
class ViewLanes:
    """The cameras a pass's lanes connect to: ``camera`` (:class:`SensorCamera`, or
    :class:`LaneCameras`: each lane's own), ``view`` each lane's view (None: one view) and
    ``count`` the views, whose images are joined view-major."""
    camera: object
    view: object
    count: int


class LaneCameras:
    """Several perspective sensors of one film size W × H for lanes that belong to different
    views, with :class:`SensorCamera`'s two methods: lane i uses camera ``view[i]`` of
    ``sensors``, whose frame and intrinsics it gathers (no lane evaluates another camera).

    The ray through film position (u, v) is Mitsuba's perspective ``sample_ray``: in camera
    space x = 2t (c_x − u/W), y = 2t (c_y − v/H) / a (t = tan(fov/2), c = ½ − o the principal
    point, a = W/H), d = normalize(x, y, 1); the world ray starts at the near plane,
    o + R d · n / d_z, heads along R d and ends at the far plane, (f − n) / d_z further (R, o the
    camera-to-world rotation and origin, n, f the clip distances). Towards a point x with camera
    coordinates (x', y', z') = M⁻¹ x it is :class:`Projection` and :meth:`Projection.importance`:
    valid for n < z' < f and a film position inside the (shifted) film."""

    def __init__(self, sensors, view: mi.UInt32, width: int, height: int):
        self.gather(CameraTable.of(sensors, width, height), view)

    @classmethod
    def from_table(cls, table: "CameraTable", view: mi.UInt32) -> "LaneCameras":
        """The cameras of lanes whose views index the rows of ``table``."""
        cams = cls.__new__(cls)
        cams.gather(table, view)
        return cams

    def gather(self, table: "CameraTable", view: mi.UInt32):
        self.width, self.height = table.width, table.height
        self.axes = [dr.gather(mi.Vector3f, table.frames, view * 4 + j) for j in range(4)]
        self.local_axes = [dr.gather(mi.Vector3f, table.inverses, view * 4 + j) for j in range(4)]
        self.tan_half, self.cx, self.cy, self.near, self.far = (
            dr.gather(mi.Float, table.intrinsics, view * 5 + j) for j in range(5))

    def __call__(self, uv, active=True):
        """The (detached) camera ray of each lane's view through film position ``uv`` (pixels)."""
        x = 2.0 * self.tan_half * (self.cx - uv.x / self.width)
        y = 2.0 * self.tan_half * (self.cy - uv.y / self.height) * (self.height / self.width)
        d = dr.normalize(mi.Vector3f(x, y, 1.0))
        right, up, forward, origin = self.axes
        direction = right * d.x + up * d.y + forward * d.z
        inv_z = dr.rcp(d.z)
        ray = mi.Ray3f(origin + direction * (self.near * inv_z), direction)
        ray.maxt = (self.far - self.near) * inv_z
        return ray

    def local(self, x):
        """Camera-space coordinates M⁻¹ x of world points ``x`` in each lane's camera."""
        a, b, c, t = self.local_axes
        return a * x.x + b * x.y + c * x.z + t

    def film(self, local):
        """Film position (pixels) of camera-space points ``local``: :class:`Projection`'s formula."""
        aspect = self.width / self.height
        return mi.Point2f(self.width * (self.cx - 0.5 * local.x / (local.z * self.tan_half)),
                          self.height * (self.cy - 0.5 * aspect * local.y / (local.z * self.tan_half)))

    def project(self, x):
        """(film position in pixels, camera-space depth z) of world points ``x`` (AD), as
        :class:`Projection` gives them, each lane in its own camera."""
        local = self.local(x)
        return self.film(local), local.z

    def direction(self, x, active):
        """(W_e, d0, film position, valid, distance) of each lane's camera towards ``x``."""
        local = self.local(x)
        aspect = self.width / self.height
        uv = self.film(local)
        valid = mi.Bool(active) & (local.z > self.near) & (local.z < self.far) & \
            (uv.x >= 0) & (uv.x <= self.width) & (uv.y >= 0) & (uv.y <= self.height)
        dist2 = dr.squared_norm(local)
        cos = local.z * dr.rsqrt(dist2)
        area = (2.0 * self.tan_half) ** 2 / aspect
        importance = dr.select(valid, dr.rcp(area * cos * cos * cos * dist2), 0.0)
        to_camera = self.axes[3] - x
        dist = dr.norm(to_camera)
        return mi.Spectrum(importance), to_camera / dist, uv, valid, dist


@dataclass
class CameraTable:
    """The cameras of several perspective sensors of one film size W × H as data, one row per
    sensor: its camera-to-world frame (columns x, y, z and the origin: 12 floats), the frame's
    inverse (12) and its intrinsics (tan(fov/2), c_x, c_y, near, far: 5). A lane gathers its
    view's row (:class:`LaneCameras`), so a function of the table and an array of view indices
    is the same function for every choice of views (what ``dr.freeze`` needs to replay it)."""
    frames: mi.Float
    inverses: mi.Float
    intrinsics: mi.Float
    width: int
    height: int

    @classmethod
    def of(cls, sensors, width: int, height: int) -> "CameraTable":
        frames, inverses, intrinsics = [], [], []
        for sensor in sensors:
            params = mi.traverse(sensor)
            M = np.array(params["to_world"].matrix, np.float64).reshape(4, 4)
            frames.append(M[:3, :4].T.ravel())
            inverses.append(np.linalg.inv(M)[:3, :4].T.ravel())
            proj = Projection(sensor)
            intrinsics.append((proj.tan_half, *proj.centre, float(params["near_clip"]), float(params["far_clip"])))
        return cls(*(jit_array(mi.Float, np.ravel(a)) for a in (frames, inverses, intrinsics)), width, height)


def table_camera_rays(table: CameraTable, views: mi.UInt32, sampler: mi.Sampler, spp: int) -> mi.Ray3f:
    """:func:`views_camera_rays` with the cameras as data: lane i belongs to the batch's view
    ``views[i // (W·H·spp)]`` (a row of ``table``) and to its pixel (i mod W·H·spp) // spp, at the
    film point (x, y) + ξ; the same samples are drawn (ξ, then the unused wavelength sample) and the
    perspective camera's weight is 1. The lane counts are literals: its caller records it once per
    film and sample count (:mod:`psdr_cli.optimisation.frozen_batch`), where an opaque scalar would be a memset
    at every replay."""
    width, height = table.width, table.height
    per_view = width * height * spp
    idx = dr.arange(mi.UInt32, per_view * dr.width(views))
    k = idx // per_view
    pixel = (idx - k * per_view) // spp
    pos = mi.Point2f(mi.Float(pixel % width), mi.Float(pixel // width)) + sampler.next_2d()
    sampler.next_1d()  # the wavelength sample of Mitsuba's sample_ray
    return LaneCameras.from_table(table, dr.gather(mi.UInt32, views, k))(pos)


def lane_views(sensors, n_samples: int) -> tuple:
    """(view, cameras) of ``n_samples`` lanes per view of ``sensors`` (one film size) traced as one
    wavefront, view-major: lane i belongs to view i // n_samples and sees it through
    :class:`LaneCameras`."""
    width, height = sensors[0].film().size()
    view = dr.arange(mi.UInt32, n_samples * len(sensors)) // dr.opaque(mi.UInt32, n_samples)
    return view, LaneCameras(sensors, view, width, height)


def camera_connection(scene: mi.Scene, camera, x, active):
    """Project x to the film of ``camera`` (:class:`SensorCamera`, :class:`LaneCameras`) and test
    that the camera sees it.

    Returns (importance W_e, direction to the camera d0, film position in pixels, camera-ray hit, mask).
    The camera ray through the film position must land on x (scale-relative tolerance).
    """
    active = mi.Bool(active)  # a copy: `&=` below must not narrow the caller's mask
    importance, d0, uv, valid, dist = camera.direction(x, active)
    width, height = camera.width, camera.height
    active &= valid & (dr.max(importance) > 0) & (uv.x >= 0) & (uv.x < width) & (uv.y >= 0) & (uv.y < height)
    si = scene.ray_intersect(camera(uv, active), active)
    active &= si.is_valid() & (dr.norm(si.p - x) < 1e-3 * dist)
    return importance, d0, uv, si, active


def connect_camera(scene: mi.Scene, camera, x, w_in, active):
    """Importance carried from the camera to a surface point x for light arriving from ``w_in``.

    Value W_e · f_s(x; w_in → d0) |n·d0| with the shading-normal correction
    |cos_sh(w_in)·(n·d0)| / |cos_sh(d0)·(n·w_in)| (light-tracing convention). Returns
    (value, film position, pixel, mask, camera-ray hit)."""
    importance, d0, uv, siC, ok = camera_connection(scene, camera, x, active)
    siC.wi = siC.to_local(d0)
    siC = bend_shading_normal(siC)  # the same shading frame the camera path sees at this point
    siC.wi = siC.to_local(w_in)
    wo = siC.to_local(d0)
    fs = siC.bsdf().eval(mi.BSDFContext(mi.TransportMode.Importance), siC, wo, ok)
    shading = dr.abs(siC.wi.z * dr.dot(d0, siC.n)) / dr.maximum(dr.abs(wo.z * dr.dot(w_in, siC.n)), 1e-12)
    value = dr.select(ok, importance * fs * shading, 0.0)
    return value, uv, dr.select(ok, film_pixel(uv, camera.width), 0), ok, siC
