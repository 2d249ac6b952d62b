"""Interior term: unidirectional path tracing with next-event estimation (NEE), in material form.

The mathematics is docs/theory.md §1 ("The interior term"). For a camera ray the estimator
returns

    L = Σ_{k=0}^{max_depth-1} β_k · [ w_bsdf,k · Le(x_k) + w_light,k · f_s(x_k) · Le(y_k) G / p_light ]

(BSDF sampling and NEE combined by the balance heuristic; the depth convention of Mitsuba's
``path`` integrator). With ``ad=True`` the vertex seen through the pixel slides along its fixed
camera ray and every later vertex is a material point (``RayFlags.FollowShape``), so that each
segment carries f_s·|n_k·ω_k|/|x_k − x_{k-1}|²·J_k over its detached value: the primal value is
the render and the product of these ratios carries dL/dθ. At every vertex on a smooth-shaded
face the terminator term is added by :func:`plane_boundary` (``terminator.py``, §8); its primal
value is 0.

Parameters (experiment keys)
----------------------------
``estimator.terms`` (list of term names, default all four)
    The term runs when ``interior`` is listed.
``estimator.spp`` (int ≥ 1, default 64)
    Paths per pixel (``psdr render`` renders its images with it too).
``scene.max_depth`` (int ≥ 1, default 2)
    Path length in segments: 1 shows emitters only, 2 is direct lighting, 3 adds one bounce.
``scene.objects[].smooth`` (bool, default false)
    Smooth shading: adds the terminator term at the object's vertices (§8).
``estimator.passes`` (int ≥ 1, default 1)
    Fewest passes each view's samples are split into (more when a pass would exceed
    :data:`.passes.AD_LANES` lanes).
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from .camera import camera_rays, views_camera_rays
from .passes import make_sampler
from .shading_frame import bend_shading_normal
from .term import Term
from .terminator import PlaneSample, has_smooth_meshes, terminator_term


def mis_weight(pdf_a, pdf_b):
    """Balance heuristic p_a / (p_a + p_b), 0 when both densities vanish."""
    return dr.detach(dr.select(pdf_a > 0, pdf_a / (pdf_a + pdf_b), 0.0))


def ratio(x):
    """x / detach(x), 1 where the detached value is 0: primal 1, derivative d(log x)."""
    xd = dr.detach(x)
    return dr.select(xd != 0, x / dr.select(xd != 0, xd, 1.0), 1.0)


def triangle_area(si: mi.SurfaceInteraction3f):
    """Area of the hit triangle, |dp_du × dp_dv| / 2 (meshes without UVs: edges of the triangle)."""
    return 0.5 * dr.norm(dr.cross(si.dp_du, si.dp_dv))


def segment_ratio(env_motion, prev_si, prev_bsdf, si, ray_d, active):
    """Derivative carrier of the segment x_{k-1} → x_k (primal 1).

    Hit: f_s(x_{k-1}, ω)·|n_k·ω|/d² · J_k with ω, d from the moving points; miss (environment):
    f_s(x_{k-1}, ω) with ω the sampled direction, turned with the environment when it rotates
    (a material direction of the environment, as in :func:`emitter_ratio`, so that NEE and
    BSDF samples of the environment use one parametrisation and their MIS weights stay valid).
    ``si.wi`` is reset to the moving −ω on hits."""
    hit = si.is_valid()
    d = si.p - prev_si.p
    dist2 = dr.squared_norm(d)
    w = dr.select(hit, d * dr.rsqrt(dr.select(hit, dist2, 1.0)), turn(env_motion, ray_d))
    si.wi = dr.select(hit, si.to_local(-w), si.wi)
    f = prev_bsdf.eval(mi.BSDFContext(), prev_si, prev_si.to_local(w), active)
    geom = dr.abs(dr.dot(si.n, w)) / dr.select(hit, dist2, 1.0) * triangle_area(si)
    return ratio(f) * dr.select(hit, ratio(geom), 1.0)


def environment_motion(scene: mi.Scene):
    """M(θ) = T(θ) T(θ0)⁻¹ of the environment's ``to_world`` when it carries derivatives (a
    rotating environment), else ``None``. M ω is the world direction of the environment's material
    direction seen along ω at θ0."""
    env = scene.environment()
    if env is None:
        return None
    params = mi.traverse(env)
    if "to_world" not in params:  # e.g. a constant environment
        return None
    T = params["to_world"]
    if not dr.grad_enabled(T.matrix):
        return None
    return T @ dr.detach(T).inverse()


def environment_texels(scene: mi.Scene) -> bool:
    """Whether the environment's texels carry derivatives (``optimize.envmap``): NEE then needs
    Le attached (Mitsuba's sampling weight Le/p is computed without derivatives; p, the density of
    the map's own importance sampling, is a function of the texels that stays detached: the samples
    are drawn from it, so d/dθ E[Le/p] = E[(dLe/dθ)/p])."""
    env = scene.environment()
    if env is None:
        return False
    params = mi.traverse(env)
    return "data" in params and dr.grad_enabled(params["data"])


def turn(motion, w):
    """The direction ω moved with the environment (ω itself for a static one)."""
    return w if motion is None else motion @ mi.Vector3f(w)


def emitter_ratio(env_motion, si, bsdf, ds, active):
    """Derivative carrier of an NEE connection x → y (primal 1): f_s(x, ω)·G(x, y).

    Area lights: y is a fixed point, ω = normalize(y − x) and G = |n_y·ω|/|y − x|² move with x.
    Environments: the sampled direction is a material direction of the environment, so a rotating
    environment turns it, ω(θ) = T(θ)T(θ0)⁻¹ω, while its radiance stays attached to it (a sharp
    sun then needs no derivative of Le across its rim)."""
    finite = ~(mi.has_flag(ds.emitter.flags(), mi.EmitterFlags.Infinite) | dr.isinf(ds.dist))
    d = ds.p - si.p
    dist2 = dr.squared_norm(d)
    w = dr.select(finite, d * dr.rsqrt(dr.select(finite, dist2, 1.0)), turn(env_motion, ds.d))
    f = bsdf.eval(mi.BSDFContext(), si, si.to_local(w), active)
    geom = dr.abs(dr.dot(ds.n, w)) / dr.select(finite, dist2, 1.0)
    return ratio(f) * dr.select(finite & ~ds.delta, ratio(geom), 1.0)


def plane_boundary(scene, sampler, si, bsdf, depth_left: int, env_motion, active):
    """The terminator term at vertex ``si`` (:func:`terminator.terminator_term`): one direction in
    its facet's plane, the radiance read just above and just below that plane with ``depth_left``
    more vertices, primal 0."""
    sample = PlaneSample(si, bsdf, sampler.next_1d(), active)
    with dr.suspend_grad():
        L_above = radiance(scene, sampler, sample.above, depth_left, sample.active)
        L_below = radiance(scene, sampler, sample.below, depth_left, sample.active)
    return terminator_term(scene, si, sample, L_above, L_below, turn(env_motion, sample.w))


def radiance(scene: mi.Scene, sampler: mi.Sampler, ray: mi.Ray3f, max_depth: int, active=True, *,
             ad: bool = False, by_depth: bool = False, hide_background: bool = False, si=None):
    """Radiance arriving along ``ray`` (Python-unrolled over ``max_depth`` path vertices).

    ``ad``: attach material-form derivatives (the ray must be detached). ``by_depth``: return the
    list [L_1, …, L_max_depth] where L_n sums the paths with n segments (L_1 is the emission seen
    directly along ``ray``). ``hide_background``: ``ray`` leaving the scene sees 0 instead of the
    environment (a camera ray of a masked photograph: the render is then colour × coverage, the
    premultiplied composite; the environment still lights every later vertex). ``si``: the first
    hits of ``ray`` when the caller traced them already (with a mask covering ``active``; not with
    ``ad``), so that they are not traced twice."""
    ctx = mi.BSDFContext()
    parts = [mi.Color3f(0.0) for _ in range(max_depth)]
    beta = mi.Color3f(1.0)
    carry = mi.Color3f(1.0)  # product of derivative carriers (primal 1)
    active = mi.Bool(active)
    prev_si = dr.zeros(mi.SurfaceInteraction3f)
    prev_bsdf = None
    prev_pdf = mi.Float(1.0)
    prev_delta = mi.Bool(True)  # the camera vertex: emission seen directly gets weight 1
    env_motion = environment_motion(scene) if ad else None
    env_texels = ad and environment_texels(scene)
    terminator = ad and has_smooth_meshes(scene)
    si = scene.ray_intersect(ray, active) if si is None else si
    for depth in range(max_depth):
        if ad and depth > 0:
            carry *= segment_ratio(env_motion, prev_si, prev_bsdf, si, ray.d, active)
        si = bend_shading_normal(si)
        # Emission at the vertex reached by BSDF sampling (or by the camera ray)
        with dr.suspend_grad():
            ds = mi.DirectionSample3f(scene, si, prev_si)
            pdf_em = scene.pdf_emitter_direction(prev_si, ds, active & ~prev_delta)
            w_bsdf = dr.select(prev_delta, 1.0, mis_weight(prev_pdf, pdf_em))
        Le = ds.emitter.eval(si, active)
        if depth == 0 and hide_background:
            Le = dr.select(si.is_valid(), Le, 0.0)
        if depth > 0 and env_motion is not None:
            Le = dr.select(si.is_valid(), Le, dr.detach(Le))  # attached to its material direction
        parts[depth] += dr.select(active, beta * carry * w_bsdf * Le, 0.0)

        active &= si.is_valid()
        if depth + 1 >= max_depth:
            break
        bsdf = si.bsdf(ray)

        # Next-event estimation
        with dr.suspend_grad():
            active_em = active & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
            ds_em, em_weight = scene.sample_emitter_direction(si, sampler.next_2d(), True, active_em)
            active_em &= ds_em.pdf != 0.0
            wo = si.to_local(ds_em.d)
            f_em, pdf_bsdf = bsdf.eval_pdf(ctx, si, wo, active_em)
            w_em = dr.select(ds_em.delta, 1.0, mis_weight(ds_em.pdf, pdf_bsdf))
        contrib = beta * carry * w_em * f_em * em_weight
        if ad:
            contrib *= emitter_ratio(env_motion, si, bsdf, ds_em, active_em)
        if env_texels:  # Le/p with Le attached to the texels, p (the texels' sampling density) detached
            contrib *= ratio(ds_em.emitter.eval_direction(si, ds_em, active_em))
        parts[depth + 1] += dr.select(active_em, contrib, 0.0)

        if terminator:  # the boundary of this vertex's facet plane (terminator.py)
            parts[depth + 1] += dr.detach(beta * carry) * plane_boundary(
                scene, sampler, si, bsdf, max_depth - depth - 1, env_motion, active)

        # BSDF sampling to the next vertex
        with dr.suspend_grad():
            bs, bsdf_weight = bsdf.sample(ctx, si, sampler.next_1d(), sampler.next_2d(), active)
            beta *= bsdf_weight
            active &= (bs.pdf > 0.0) & (dr.max(beta) > 0.0)
            prev_pdf = bs.pdf
            prev_delta = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
            ray = si.spawn_ray(si.to_world(bs.wo))
        prev_si, prev_bsdf = si, bsdf
        if ad:
            si = scene.ray_intersect(ray, mi.RayFlags.All | mi.RayFlags.FollowShape, False, active)
        else:
            si = scene.ray_intersect(ray, active)
    if by_depth:
        return parts
    total = parts[0]
    for p in parts[1:]:
        total = total + p
    return total


def render_pass(scene: mi.Scene, sensor: mi.Sensor, width: int, height: int, spp: int,
                max_depth: int, seed: int, *, hide_background: bool = False) -> np.ndarray:
    """One primal pass of the renderer (:func:`psdr_cli.rendering.render.render_view`): the sum over ``spp``
    samples of every pixel, as a (H, W, 3) float64 array."""
    sampler = make_sampler(seed, width * height * spp)
    ray, weight = camera_rays(sensor, sampler, width, height, spp)
    L = weight * radiance(scene, sampler, ray, max_depth, hide_background=hide_background)
    dr.eval(L)  # one kernel for the three channels (each block sum would trace the paths again)
    sums = [dr.block_sum(L[c], spp, mode="evaluated") for c in range(3)]
    dr.eval(sums)
    return np.stack([np.asarray(s, np.float64) for s in sums], axis=-1).reshape(height, width, 3)


def views_pass(scene: mi.Scene, sensors, width: int, height: int, spp: int, max_depth: int, seed: int, *,
               hide_background: bool = False) -> mi.Float:
    """One primal pass of several views in one wavefront (:func:`.camera.views_camera_rays`): the
    sum over ``spp`` samples of every pixel, flat (views · H · W · 3) on the device, view-major."""
    sampler = make_sampler(seed, width * height * spp * len(sensors))
    ray, weight = views_camera_rays(sensors, sampler, width, height, spp)
    L = weight * radiance(scene, sampler, ray, max_depth, hide_background=hide_background)
    dr.eval(L)  # one kernel for the three channels
    return dr.ravel(mi.Color3f([dr.block_sum(L[c], spp, mode="evaluated") for c in range(3)]))


def split_views(image: mi.Float, count: int) -> list:
    """The ``count`` equal view-major parts of a flat image of several views (AD gathers)."""
    n = dr.width(image) // count
    index = dr.arange(mi.UInt32, n)
    return [dr.gather(mi.Float, image, index + dr.opaque(mi.UInt32, k * n)) for k in range(count)]


def estimate(scene, edges, view: int, spp: int, seed: int, estimator, max_depth: int, *, guide=None) -> mi.Float:
    """One pass of the interior term (:class:`~.term.Term` signature): the mean of ``spp``
    material-form path samples per pixel (flat W·H·3, AD), whose primal value is the render."""
    sensor = scene.sensors[view]
    width, height = sensor.film().size()
    sampler = make_sampler(seed, width * height * spp)
    ray, weight = camera_rays(sensor, sampler, width, height, spp)
    L = weight * radiance(scene.mi_scene, sampler, ray, max_depth, ad=True,
                          hide_background=scene.config.hide_background)
    dr.eval(L)  # one kernel for the three channels' primal values
    return dr.ravel(mi.Color3f([dr.block_sum(L[c], spp, mode="evaluated") / spp for c in range(3)]))


def estimate_views(scene, edges, views, spp: int, seed: int, estimator, max_depth: int) -> list:
    """One pass of the interior term for several ``views`` traced as one wavefront (the samples
    of :func:`estimate`, drawn from one sampler seeded with ``seed``): a flat W·H·3 AD image per
    view, whose primal value is the render."""
    width, height = scene.resolution
    sampler = make_sampler(seed, width * height * spp * len(views))
    ray, weight = views_camera_rays([scene.sensors[v] for v in views], sampler, width, height, spp)
    L = weight * radiance(scene.mi_scene, sampler, ray, max_depth, ad=True,
                          hide_background=scene.config.hide_background)
    dr.eval(L)  # one kernel for the three channels' primal values
    image = dr.ravel(mi.Color3f([dr.block_sum(L[c], spp, mode="evaluated") / spp for c in range(3)]))
    return split_views(image, len(views))


TERM = Term("interior", samples_key="spp", stream=1, estimate=estimate, estimate_views=estimate_views, renders=True)
