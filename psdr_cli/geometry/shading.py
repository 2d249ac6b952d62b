"""Smooth shading (interpolated vertex normals) and what its gradients cover.

A smooth-shaded triangle is still a flat facet: a direction ω leaving a point x of face f is
blocked by the mesh itself as soon as n_g·ω < 0, while the shading normal can still see it
(n_s·ω > 0). The integrand therefore jumps where ω crosses the facet's plane, and because that
plane turns from face to face, pixels near the shadow terminator jump across every mesh edge.
Both discontinuities are estimated: the first by the terminator term
(``estimators/terminator.py``), the second by the primary term, which samples every non-flat
edge of smooth meshes (docs/theory.md §8). The terminator term covers reflection only (the half
of the facet's plane the shading normal sees), so a moving smooth-shaded object whose BSDF
transmits light is flagged with one warning.
"""
from __future__ import annotations

import mitsuba as mi


def smooth_objects(scene) -> list:
    """Names of the boundary-term (moving) objects that are smooth-shaded."""
    return [n for n, om in scene.objects.items() if om.edges and getattr(om.config, "smooth", False)]


def transmits(bsdf) -> bool:
    """Whether a BSDF has a transmission lobe."""
    return bsdf is not None and mi.has_flag(bsdf.flags(), mi.BSDFFlags.Transmission)


def transmissive_smooth_objects(scene) -> list:
    """Names of the moving smooth-shaded objects whose BSDF transmits light."""
    shapes = {s.id(): s for s in scene.mi_scene.shapes()}
    return [n for n in smooth_objects(scene) if n in shapes and transmits(shapes[n].bsdf())]


def smooth_warning(scene) -> str | None:
    """One-line warning for gradients of smooth-shaded transmitting objects (``None`` when there
    are none)."""
    names = transmissive_smooth_objects(scene)
    if not names:
        return None
    return (f"object(s) {', '.join(repr(n) for n in names)} are smooth-shaded and transmit light: the "
            "terminator term covers reflection only, so the gradient can be biased (docs/gradients.md); "
            "use smooth: false for exact gradients")
