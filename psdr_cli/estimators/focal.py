"""The focal scale of a perspective camera: its value in Mitsuba's field of view, its derivative in psdr's.

A focal scale s multiplies the focal length, f' = s·f, and keeps the principal point: for a
horizontal field of view φ,

    tan(φ'/2) = tan(φ/2) / s,

so a camera-space direction (x, y, z) lands on the film where (x/s, y/s, z) did, and the
pinhole's importance W_e = 1 / (A cos³θ d²) with A = (2 tan(φ/2))² / a grows as s² (A ∝ 1/s²).

Mitsuba's perspective sensor does not differentiate its field of view (``x_fov`` is a value
only), so s is split in two:

- its *value* is written into the sensor's ``x_fov`` (every path that only reads the camera —
  Mitsuba's ``sample_ray``/``sample_direction``, :class:`.camera.CameraTable`, renders — sees the
  changed focal length as it is);
- its *derivative* rides in a factor σ = s / detach(s) (value 1) that the sensor carries while
  it is attached (:func:`attach`), and that psdr's camera paths apply on top of Mitsuba's:
  :func:`refocus` re-aims a camera ray, :func:`film_scale` moves a film position about the
  principal point, and the importance is multiplied by σ².

A sensor carries σ only while a derivative is taken (``psdr grad``'s ``parameter: {camera: i,
kind: focal}``, the corrections of ``optimize.cameras.focal`` while attached); otherwise
:func:`factor` is None and the camera paths are Mitsuba's own. Passes that gather their cameras as
constants (:class:`.camera.LaneCameras`) hold the value only, like a moving pose.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi


def refocus(sensor, ray: mi.Ray3f, sigma) -> mi.Ray3f:
    """``ray`` of ``sensor`` (from its centre's near plane) re-aimed for the focal factor σ: in
    camera space d = (x, y, z) → normalize(x/σ, y/σ, z), then back to the world through the
    sensor's (possibly AD-attached) to_world; the ray starts on the near plane n and ends on the
    far plane f, as Mitsuba's: o + d·n/d_z, maxt (f − n)/d_z."""
    to_world = sensor.world_transform()
    local = to_world.inverse() @ mi.Vector3f(ray.d)
    d = dr.normalize(mi.Vector3f(local.x / sigma, local.y / sigma, local.z))
    direction = to_world @ d
    inv_z = dr.rcp(d.z)
    near, far = float(sensor.near_clip()), float(sensor.far_clip())
    out = mi.Ray3f(to_world.translation() + direction * (near * inv_z), direction)
    out.maxt = (far - near) * inv_z
    return out


def film_scale(uv, centre, sigma):
    """The film position (pixels) ``uv`` at focal factor σ: centre + σ (uv − centre), about the
    principal point ``centre`` (pixels)."""
    cx, cy = centre
    return mi.Point2f(cx + sigma * (uv.x - cx), cy + sigma * (uv.y - cy))
