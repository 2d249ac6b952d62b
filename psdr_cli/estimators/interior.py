"""Interior term: unidirectional path tracing with next-event estimation (NEE), in material form.

For a camera ray the estimator returns

    L = Σ_{k=0}^{max_depth-1} β_k · [ w_bsdf,k · Le(x_k) + w_light,k · f_s(x_k) · Le(y_k) G / p_light ]

where β_k is the BSDF-sampling throughput up to vertex x_k, the first term is emission hit by the
ray that reached x_k (environment included on a miss) and the second is NEE towards a sampled
emitter point y_k. Both are combined with the balance heuristic w_a = p_a / (p_bsdf + p_light);
delta lobes and delta emitters keep weight 1. ``max_depth = 2`` is direct lighting only, the same
convention as Mitsuba's ``path`` integrator.

Derivatives (``ad=True``) follow the material form of the path integral. The camera vertex x_1 is
tied to the pixel (it slides along the fixed camera ray); every later vertex x_k is a material
point (``RayFlags.FollowShape``: fixed barycentrics on a moving triangle), so each segment
x_{k-1} → x_k contributes the factors

    f_s(x_{k-1}, ω_k) · |n_k · ω_k| / |x_k − x_{k-1}|² · J_k,   J_k = A_k / detach(A_k),

with ω_k = normalize(x_k − x_{k-1}) recomputed from the moving points, divided by their detached
values (sampling densities and MIS weights stay detached). The primal value is unchanged; the
product of these ratios carries dL/dθ. NEE towards an area-light point y uses
f_s · Le · |n_y·ω| / |y − x|² the same way; environment directions are solid-angle samples and
only f_s and Le(ω) (e.g. a rotating environment) carry derivatives.

Smooth shading (experimental, ``SMOOTH_TERMINATOR``, off by default): f_s(x_k, ω) is multiplied
by the terminator factor T(x_k; ω_i, ω) of :func:`terminator_factor` (1 on flat surfaces), in the
primal value and in the carriers, so that the integrand is continuous where the facet of x_k
starts to block ω (docs/theory.md §8).
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi


def mis_weight(pdf_a, pdf_b):
    """Balance heuristic p_a / (p_a + p_b), 0 when both densities vanish."""
    return dr.detach(dr.select(pdf_a > 0, pdf_a / (pdf_a + pdf_b), 0.0))


def ratio(x):
    """x / detach(x), 1 where the detached value is 0: primal 1, derivative d(log x)."""
    xd = dr.detach(x)
    return dr.select(xd != 0, x / dr.select(xd != 0, xd, 1.0), 1.0)


#: Whether smooth-shaded vertices use the terminator factor of :func:`terminator_factor`.
#: Off: experimental, measured not yet unbiased (docs/gradients.md, "Smooth shading"); with it
#: off every estimator is unchanged (T ≡ 1, smooth meshes keep silhouette-only primary edges).
SMOOTH_TERMINATOR = False

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


def terminator_factor(si: mi.SurfaceInteraction3f, view, w):
    """Smooth-shading terminator factor T(x; view, ω) ∈ [0, 1] for light leaving along ω (Chiang,
    Li and Burley 2019, smoothed): with n_g and n_s the geometric and (bent) shading normals turned
    to the ``view`` side, a = n_g·ω, b = n_s·ω, c = n_g·n_s and σ = sign(b),

        G = clamp(σa / (|b| · max(c, 10⁻⁶)), 0, 1),   T = −G³ + G² + G.

    A smooth-shaded triangle is a flat facet, so the mesh blocks ω as soon as σa < 0 while the
    shading normal still sees it (|b| > 0): without T the contribution jumps to 0 across the curve
    n_g·(y − x) = 0 inside faces. With T it goes to 0 continuously (T ≈ G ∝ a as a → 0⁺). T = 1
    where the facet does not graze (G ≥ 1; T' = 0 there too), on flat-shaded surfaces (n_s = n_g)
    and on misses. T depends on n_g, so it jumps across the mesh edges of the terminator region:
    the primary term then samples every non-flat edge of smooth meshes (docs/theory.md §8).
    Applied to the light side of every vertex: NEE and BSDF-sampled directions of the path tracer,
    and the direction light arrives from in camera connections and light-tracing walks. While
    ``SMOOTH_TERMINATOR`` is off this is the constant 1 (nothing is traced into the kernels)."""
    if not SMOOTH_TERMINATOR:
        return 1.0
    n_g, n_s = si.n, si.sh_frame.n
    s = dr.select(dr.dot(n_g, view) < 0, -1.0, 1.0)
    b = s * dr.dot(n_s, w)
    sigma = dr.select(b < 0, -1.0, 1.0)
    a = sigma * s * dr.dot(n_g, w)
    c = dr.dot(n_g, n_s)
    G = dr.clip(a / dr.maximum(dr.abs(b) * dr.maximum(c, 1e-6), 1e-12), 0.0, 1.0)
    smooth = si.is_valid() & (dr.norm(n_s - n_g) > 1e-6)
    return dr.select(smooth, G * (1.0 + G - G * G), 1.0)


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
    f = f * terminator_factor(prev_si, prev_si.to_world(prev_si.wi), w)
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
    f = bsdf.eval(mi.BSDFContext(), si, si.to_local(w), active) * terminator_factor(si, si.to_world(si.wi), w)
    geom = dr.abs(dr.dot(ds.n, w)) / dr.select(finite, dist2, 1.0)
    return ratio(f) * dr.select(finite & ~ds.delta, ratio(geom), 1.0)


def radiance(scene: mi.Scene, sampler: mi.Sampler, ray: mi.Ray3f, max_depth: int, active=True,
             ad: bool = False, by_depth: bool = False):
    """Radiance arriving along ``ray`` (Python-unrolled over ``max_depth`` path vertices).

    ``ad``: attach material-form derivatives (the ray must be detached). ``by_depth``: return the
    list [L_1, …, L_max_depth] where L_n sums the paths with n segments (L_1 is the emission seen
    directly along ``ray``)."""
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
    si = scene.ray_intersect(ray, active)
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
            f_em *= terminator_factor(si, si.to_world(si.wi), ds_em.d)
            w_em = dr.select(ds_em.delta, 1.0, mis_weight(ds_em.pdf, pdf_bsdf))
        contrib = beta * carry * w_em * f_em * em_weight
        if ad:
            contrib *= emitter_ratio(env_motion, si, bsdf, ds_em, active_em)
        parts[depth + 1] += dr.select(active_em, contrib, 0.0)

        # BSDF sampling to the next vertex
        with dr.suspend_grad():
            bs, bsdf_weight = bsdf.sample(ctx, si, sampler.next_1d(), sampler.next_2d(), active)
            beta *= bsdf_weight * terminator_factor(si, si.to_world(si.wi), si.to_world(bs.wo))
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
