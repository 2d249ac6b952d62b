"""``scene.cameras``: cameras and ``orbit:`` rings of cameras."""
from __future__ import annotations

import math
from dataclasses import dataclass

from .limits import MAX_COORD, MAX_PRINCIPAL_OFFSET
from .values import Section, Where, describe, finite, integer, list_of, number, unit, vector


@dataclass
class CameraConfig:
    origin: tuple
    target: tuple
    up: tuple = (0.0, 0.0, 1.0)
    fov: float = 40.0  # horizontal, degrees
    #: Mitsuba's ``principal_point_offset_x/y``: the principal point sits at pixel
    #: (W·(½ − ox), H·(½ − oy)), so a positive offset moves it left / up (fractions of the film).
    principal_point: tuple = (0.0, 0.0)


def principal_point(value, where):
    """``principal_point: [ox, oy]``: Mitsuba's principal point offset, fractions of the film's
    width and height (not pixels), each within ±:data:`MAX_PRINCIPAL_OFFSET`."""
    ok = isinstance(value, (list, tuple)) and len(value) == 2 and all(
        isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)
    if not ok:
        raise where.fail(f"expected [ox, oy], two numbers (fractions of the film width and height), "
                         f"got {describe(value)}")
    if not all(finite(v) and abs(v) <= MAX_PRINCIPAL_OFFSET for v in value):
        raise where.fail(f"expected two finite numbers within ±{MAX_PRINCIPAL_OFFSET:g} (fractions of the film "
                         f"width and height, not pixels), got {describe(list(value))}")
    return tuple(float(v) for v in value)


def _check_camera(cam: CameraConfig, where: Where) -> CameraConfig:
    d = [t - o for t, o in zip(cam.target, cam.origin)]
    length = math.sqrt(sum(c * c for c in d))
    if length < 1e-9 * (1 + max(abs(c) for c in cam.origin)):
        raise where.fail(f"origin and target are the same point {list(cam.origin)}; the camera needs a view direction")
    cross = (d[1] * cam.up[2] - d[2] * cam.up[1], d[2] * cam.up[0] - d[0] * cam.up[2],
             d[0] * cam.up[1] - d[1] * cam.up[0])
    if math.sqrt(sum(c * c for c in cross)) < 1e-6 * length * math.sqrt(sum(c * c for c in cam.up)):
        raise where.fail("'up' is parallel to the view direction (target - origin)")
    return cam


def orbit_cameras(count, radius, elevation_deg, azimuth_deg, target, fov, up=(0.0, 0.0, 1.0)):
    """``count`` cameras evenly spaced in azimuth on a circle of ``radius`` around ``target``.

    Position_i = target + radius·(cos e·cos a_i·X + cos e·sin a_i·Y + sin e·Up), a_i = a_0 + 360°·i/count,
    with (X, Y, Up) a right-handed frame around ``up``.
    """
    upn = unit(up)
    ref = (1.0, 0.0, 0.0) if abs(upn[0]) < 0.9 else (0.0, 1.0, 0.0)
    dot = sum(a * b for a, b in zip(ref, upn))
    x = unit(tuple(r - dot * u for r, u in zip(ref, upn)))
    y = (upn[1] * x[2] - upn[2] * x[1], upn[2] * x[0] - upn[0] * x[2], upn[0] * x[1] - upn[1] * x[0])
    e = math.radians(elevation_deg)
    cams = []
    for i in range(count):
        a = math.radians(azimuth_deg + 360.0 * i / count)
        dirv = [math.cos(e) * math.cos(a) * x[k] + math.cos(e) * math.sin(a) * y[k] + math.sin(e) * upn[k]
                for k in range(3)]
        origin = tuple(target[k] + radius * dirv[k] for k in range(3))
        cams.append(CameraConfig(origin=origin, target=tuple(target), up=upn, fov=fov))
    return cams


def parse_cameras(value, where, up=(0.0, 0.0, 1.0)) -> list:
    """A list of cameras and ``orbit:`` rings; a single ``{orbit: {...}}`` mapping is accepted
    as a one-item list. ``up`` is the default up direction (the scene's up axis)."""
    if isinstance(value, dict) and set(value) == {"orbit"}:
        value = [value]
    items = list_of(lambda v, w: (v, w), min_len=1)(value, where)
    cams = []
    for v, w in items:
        sec = Section(v, w)
        if sec.has("orbit"):
            orb = Section(sec.get("orbit", lambda x, _: x), w.child("orbit"))
            ring = orbit_cameras(
                count=orb.get("count", integer(1, 4096)),
                radius=orb.get("radius", number(positive=True, maximum=MAX_COORD)),
                elevation_deg=orb.get("elevation_deg", number(minimum=-89.9, maximum=89.9), 20.0),
                azimuth_deg=orb.get("azimuth_deg", number(), 0.0),
                target=orb.get("target", vector(3), (0.0, 0.0, 0.0)),
                fov=orb.get("fov", number(positive=True, maximum=179), 40.0),
                up=orb.get("up", vector(3, nonzero=True), up),
            )
            orb.done()
            sec.done()
            cams.extend(ring)
            continue
        cam = CameraConfig(
            origin=sec.get("origin", vector(3)),
            target=sec.get("target", vector(3)),
            up=sec.get("up", vector(3, nonzero=True), up),
            fov=sec.get("fov", number(positive=True, maximum=179), 40.0),
            principal_point=sec.get("principal_point", principal_point, (0.0, 0.0)),
        )
        sec.done()
        cams.append(_check_camera(cam, w))
    return cams
