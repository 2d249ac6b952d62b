"""Interior term: unidirectional path tracing with next-event estimation (NEE).

For a camera ray the estimator returns

    L = Σ_{k=0}^{max_depth-1} β_k · [ w_bsdf,k · Le(x_k) + w_light,k · f_s(x_k) · Le(y_k) G / p_light ]

where β_k is the BSDF-sampling throughput up to vertex x_k, the first term is emission hit by the
ray that reached x_k (environment included on a miss) and the second is NEE towards a sampled
emitter point y_k. Both are combined with the balance heuristic w_a = p_a / (p_bsdf + p_light);
delta lobes and delta emitters keep weight 1. ``max_depth = 2`` is direct lighting only, the same
convention as Mitsuba's ``path`` integrator.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi


def mis_weight(pdf_a, pdf_b):
    """Balance heuristic p_a / (p_a + p_b), 0 when both densities vanish."""
    return dr.detach(dr.select(pdf_a > 0, pdf_a / (pdf_a + pdf_b), 0.0))


def radiance(scene: mi.Scene, sampler: mi.Sampler, ray: mi.Ray3f, max_depth: int,
             active=True) -> mi.Color3f:
    """Radiance arriving along ``ray`` (Python-unrolled over ``max_depth`` path vertices)."""
    ctx = mi.BSDFContext()
    L = mi.Color3f(0.0)
    beta = mi.Color3f(1.0)
    active = mi.Bool(active)
    prev_si = dr.zeros(mi.SurfaceInteraction3f)
    prev_pdf = mi.Float(1.0)
    prev_delta = mi.Bool(True)  # the camera vertex: emission seen directly gets weight 1
    si = scene.ray_intersect(ray, active)
    for depth in range(max_depth):
        # Emission at the vertex reached by BSDF sampling (or by the camera ray)
        ds = mi.DirectionSample3f(scene, si, prev_si)
        pdf_em = scene.pdf_emitter_direction(prev_si, ds, active & ~prev_delta)
        w_bsdf = dr.select(prev_delta, 1.0, mis_weight(prev_pdf, pdf_em))
        L += dr.select(active, beta * w_bsdf * ds.emitter.eval(si, active), 0.0)

        active &= si.is_valid()
        if depth + 1 >= max_depth:
            break
        bsdf = si.bsdf(ray)

        # Next-event estimation
        active_em = active & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
        ds_em, em_weight = scene.sample_emitter_direction(si, sampler.next_2d(), True, active_em)
        active_em &= ds_em.pdf != 0.0
        wo = si.to_local(ds_em.d)
        f_em, pdf_bsdf = bsdf.eval_pdf(ctx, si, wo, active_em)
        w_em = dr.select(ds_em.delta, 1.0, mis_weight(ds_em.pdf, pdf_bsdf))
        L += dr.select(active_em, beta * w_em * f_em * em_weight, 0.0)

        # BSDF sampling to the next vertex
        bs, bsdf_weight = bsdf.sample(ctx, si, sampler.next_1d(), sampler.next_2d(), active)
        beta *= bsdf_weight
        active &= (bs.pdf > 0.0) & (dr.max(beta) > 0.0)
        prev_si = si
        prev_pdf = bs.pdf
        prev_delta = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
        ray = si.spawn_ray(si.to_world(bs.wo))
        si = scene.ray_intersect(ray, active)
    return L
