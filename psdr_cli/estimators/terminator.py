"""Terminator term: the boundary that smooth shading adds to the interior term.

The mathematics is docs/theory.md §8. A smooth-shaded triangle f is still a flat facet: at a
path vertex x on f the facet blocks the directions below its plane that the interpolated shading
normal still accepts, so the segment integrand jumps on the curve g(y) = n·(y − x) = 0, which
moves with f. Per unit angle φ of the direction ω in the plane of f the missing derivative is

    ∂_θ I_T = ∫_0^{2π} f_s(x, ω) · [ L⁺ · ∂_θ g(y⁺) / r⁺  −  L⁻ · ∂_θ g(y⁻) / r⁻ ] dφ,

y^± being what rays leaving x just above and just below the plane reach (the derivation, the
environment, closed and open meshes: §8). It is estimated with one direction per vertex, drawn
∝ n_s·ω (:class:`PlaneSample`); the estimate has primal value 0 and carries only the derivative
(each ∂_θ g enters as g − detach(g)). Only reflection is covered: smooth meshes with a
transmitting BSDF are warned about (:mod:`psdr_cli.geometry.shading`).

Parameters (experiment keys)
----------------------------
None of its own: :func:`.interior.radiance` adds the term at every smooth vertex of the
interior term's paths (``estimator.terms``, ``estimator.spp``, ``estimator.passes`` as there).

``scene.objects[].smooth`` (bool, default false)
    Smooth shading (for a Mitsuba XML scene: meshes with vertex normals); without a smooth mesh
    the term is not traced.
``scene.max_depth`` (int ≥ 1, default 2)
    L^± are read with the path depth left at the vertex.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

#: Distance of the two side rays from the facet's plane, relative to the scene's coordinates
#: (1 + max |x_i|), well above float32 round-off and far below any feature size.
SIDE_OFFSET = 1e-4


def is_smooth(si: mi.SurfaceInteraction3f):
    """Whether the shading normal differs from the facet normal (an interpolated normal)."""
    return si.is_valid() & (dr.norm(si.sh_frame.n - si.n) > 1e-6)


def facet_normal(si: mi.SurfaceInteraction3f):
    """The facet normal n turned to the side the path arrived from (sign detached)."""
    view = si.to_world(si.wi)
    return si.n * dr.detach(dr.select(dr.dot(si.n, view) < 0, -1.0, 1.0))


def has_smooth_meshes(scene: mi.Scene) -> bool:
    """Whether any mesh of the scene interpolates vertex normals (else the term is 0 everywhere
    and is not traced at all)."""
    return any(shape.is_mesh() and shape.has_vertex_normals() for shape in scene.shapes())


class PlaneSample:
    """One direction ω in the plane of the facet at x, f_s(x, ω), and the two rays that read the
    plane's sides. ``active``: smooth vertices where f_s(x, ω) ≠ 0.

    Only the half of the plane's circle that the shading normal n_s sees can carry f_s ≠ 0 (for
    a BSDF that only reflects). With t the direction of n_s projected into the plane and
    b = n × t, ω = cos α·t + sin α·b with α = asin(2u − 1) has density p(α) = cos α / 2 on
    (−π/2, π/2), proportional to n_s·ω = |n_s − (n_s·n)n| cos α: a diffuse f_s is sampled
    exactly."""

    def __init__(self, si: mi.SurfaceInteraction3f, bsdf: mi.BSDF, u, active):
        with dr.suspend_grad():
            n = dr.detach(facet_normal(si))
            n_s = dr.detach(si.sh_frame.n)
            t = dr.normalize(n_s - dr.dot(n_s, n) * n)
            b = dr.cross(n, t)
            sin_a = 2.0 * u - 1.0
            cos_a = dr.safe_sqrt(1.0 - sin_a * sin_a)
            self.w = cos_a * t + sin_a * b
            self.weight = dr.select(cos_a > 0.0, 2.0 / dr.maximum(cos_a, 1e-12), 0.0)  # 1 / p(α)
            self.active = mi.Bool(active) & is_smooth(si) & (cos_a > 0.0)
            self.f = dr.detach(bsdf.eval(mi.BSDFContext(), si, si.to_local(self.w), self.active))
            self.active &= dr.max(self.f) > 0.0
            p = dr.detach(si.p)
            eps = SIDE_OFFSET * (1.0 + dr.max(dr.abs(p)))
            self.above = mi.Ray3f(p + eps * n, self.w)
            self.below = mi.Ray3f(p - eps * n, self.w)


def plane_rate(scene: mi.Scene, si: mi.SurfaceInteraction3f, ray: mi.Ray3f, w_env, active):
    """∂_θ g / r along one side ray, as g/r − detach(g/r) (primal 0): g = n·(y − x) with y the
    material point the ray reaches (``FollowShape``), r = |y − x| detached; on a miss g = n·ω_env
    (``w_env``: the ray direction turned with a rotating environment)."""
    hit = scene.ray_intersect(ray, mi.RayFlags.All | mi.RayFlags.FollowShape, False, active)
    found = hit.is_valid()
    n = facet_normal(si)
    d = hit.p - si.p
    r = dr.detach(dr.norm(d))
    g = dr.select(found, dr.dot(n, d) / dr.select(found, r, 1.0), dr.dot(n, w_env))
    return dr.select(active, g - dr.detach(g), 0.0)


def terminator_term(scene: mi.Scene, si: mi.SurfaceInteraction3f, sample: PlaneSample,
                    L_above, L_below, w_env):
    """f_s(x, ω)·[L⁺ ∂_θ g⁺/r⁺ − L⁻ ∂_θ g⁻/r⁻]·2π for one plane sample (primal 0). ``L_above`` and
    ``L_below`` are radiance estimates along ``sample.above`` and ``sample.below``."""
    active = sample.active
    rate_above = plane_rate(scene, si, sample.above, w_env, active)
    rate_below = plane_rate(scene, si, sample.below, w_env, active)
    jump = dr.detach(L_above) * rate_above - dr.detach(L_below) * rate_below
    return dr.select(active, sample.weight * sample.f * jump, 0.0)
