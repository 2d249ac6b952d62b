"""Shading frames that face the viewer, shared by camera paths (:mod:`.interior`) and camera
connections (:mod:`.camera`), so that both see the same shading frame at a point."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

#: Smallest |cos| between a shading normal and the viewing direction (see ``bend_shading_normal``).
MIN_SHADING_COS = 0.02


def bend_shading_normal(si: mi.SurfaceInteraction3f):
    """Keep interpolated shading normals facing the viewer: with s = sign(n_g·ω_i) and
    c = s·(n_s·ω_i), a normal with c < δ becomes normalize(n_s + s(δ − c) ω_i).

    Without this, the region near a smooth mesh's silhouette where n_s turns away from the viewer
    renders black (BSDFs reject ω_i below the shading hemisphere), and the edge of that band is
    an image discontinuity that follows no mesh edge, so no boundary term could account for it.
    The bend is continuous (no change at c = δ) and leaves flat shading (n_s = n_g) untouched
    unless the view is within δ of grazing."""
    valid = si.is_valid()
    wi = si.to_world(si.wi)
    smooth = dr.norm(si.sh_frame.n - si.n) > 1e-6
    s = dr.sign(dr.dot(si.n, wi))
    c = s * dr.dot(si.sh_frame.n, wi)
    bend = valid & smooth & (c < MIN_SHADING_COS)
    n = dr.normalize(si.sh_frame.n + s * (MIN_SHADING_COS - c) * wi)
    frame = mi.Frame3f(dr.select(bend, n, si.sh_frame.n))
    # Misses keep their fields untouched (their wi is the world direction the environment reads)
    si.wi = dr.select(bend, frame.to_local(wi), si.wi)
    si.sh_frame = dr.select(bend, frame, si.sh_frame)
    return si
