"""Smooth shading (interpolated vertex normals) and the discontinuities it adds.

A smooth-shaded triangle is still a flat facet: a direction ω leaving a point x of face f is
blocked by the mesh itself as soon as n_g·ω < 0, while the shading normal can still see it
(n_s·ω > 0). Next-event and BSDF-sampled contributions therefore jump from f_s·Le·|n_s·ω|·G to 0
across the curve {x ∈ f : n_g·normalize(y − x) = 0} inside every face near the shadow terminator.
That curve lies on no mesh edge and moves with θ whenever the light direction seen from the
surface changes (translation under an area light, rotation under any light), so neither the
edge-based boundary terms nor the interior term account for it; Mitsuba's ``prb_projective``
has the same gap. Until an estimator for it exists, a gradient of a smooth-shaded object is
flagged with one warning.
"""
from __future__ import annotations


def smooth_objects(scene) -> list:
    """Names of the boundary-term (moving) objects that are smooth-shaded."""
    return [n for n, om in scene.objects.items() if om.edges and getattr(om.config, "smooth", False)]


def smooth_warning(scene) -> str | None:
    """One-line warning for gradients of smooth-shaded objects (``None`` when there are none)."""
    names = smooth_objects(scene)
    if not names:
        return None
    return (f"object(s) {', '.join(repr(n) for n in names)} are smooth-shaded: the self-shadowing edge inside "
            "their faces (shadow terminator) is not differentiated and the gradient can be biased "
            "(docs/gradients.md); use smooth: false for exact gradients")
