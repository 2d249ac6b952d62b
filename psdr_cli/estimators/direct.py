"""Direct boundary term: boundary segments whose source end lies on an emitter (docs/theory.md §3).

A segment (x^B on an edge, direction ω, drawn as in §2) must reach emission at x^S along +ω (an
area light or the environment) and a surface point x^D seen by the camera along −ω. The sample
adds (W·H/N)·(v − detach(v)) to the pixel of x^D, so primal images are unchanged and only
derivatives flow (forward and reverse mode alike), with

    v = G · t_D sinφ · σ · (m̂ · ω(θ)),   ω(θ) = normalize(x^B(θ) − x^D_λ(θ)),   λ = t_S/(t_S + t_D),
    G = W_e(x^D) · f_s(x^D; ω → camera)|n_D·d0| · Le(x^S, −ω) / (p(x^B) p(ω)).

The notation, the lever λ (1 for the environment), the form for a rotating environment and why
it holds for static sources are in §3. The techniques (``light``, ``dir``, and ``mis`` with the
balance heuristic on the unguided densities) are §2 and §6; guided sampling (u drawn from a
guide g, the sample divided by g(u)) is §5.

Parameters (experiment keys)
----------------------------
``estimator.terms`` (list of term names, default all four)
    The term runs when ``direct`` is listed.
``estimator.boundary_spp`` (int ≥ 1, default 16)
    Boundary segments per pixel of each view; with ``mis`` pairs of one ``light`` and one
    ``dir`` sample.
``estimator.sampling`` (``light`` | ``dir`` | ``mis``, default ``mis``)
    Emitter sampling, wedge sampling, or one sample of each per pair (§6).
``estimator.guiding`` (``auto`` | ``none`` | ``grid`` | ``kdtree``, default ``auto``)
    Guide of each technique's primary samples (§5; ``auto`` picks by the size of one pass,
    :mod:`psdr_cli.guiding.auto`). In ``psdr optimize`` ``auto`` guides nothing and ``kdtree``
    trees are fitted to the loop's own samples (:mod:`psdr_cli.guiding.loop_fed`).
``estimator.guide_epsilon`` (float in [0, 1], default 0.05)
    Uniform share ε of every guide.
``estimator.kdtree.*``, ``estimator.grid.*``
    Build parameters of the guides (:mod:`psdr_cli.guiding.kdtree`, :mod:`psdr_cli.guiding.grid`);
    ``kdtree.technique_share`` (default 0.3) lets the two MIS trees share their edge profile.
``estimator.edge_sort`` (bool, default false)
    Order the edges into chains (:mod:`.boundary_sampling`, §5).
``estimator.passes`` (int ≥ 1, default 1)
    Fewest passes each view's samples are split into (more when a pass would exceed
    :data:`.passes.AD_LANES` lanes).
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from .boundary_sampling import (BoundaryEdges, EdgeDraw, EdgeSample, edge_draw, in_wedge, normalize, pdf_wedge,
                                primary_sample, ray_origin, sample_edge_point, sample_wedge)
from .camera import SensorCamera, ViewLanes, connect_camera, lane_views
from .interior import environment_motion, split_views, turn
from .sample_log import SampleLog
from .term import GuideTarget, Term, boundary_pass



def emitter_pdf(scene: mi.Scene, xB, siS, active):
    """p_light(ω) in solid angle at x^B for a direction whose ray hit siS (or escaped)."""
    it = dr.zeros(mi.Interaction3f)
    it.p = xB
    ds = mi.DirectionSample3f(scene, siS, it)
    return scene.pdf_emitter_direction(it, ds, active)


def segment_weight(scene, camera, edge: EdgeSample, w, densities, origin, light_point, *, mis: bool):
    """Everything detached for one technique's samples: returns (coef, m̂, uv, pixel, mask, x^D,
    env, λ) with ``env`` the lanes whose source is the environment and λ = t_S/(t_S + t_D) the
    lever of the detector end's motion (1 for the environment; see :func:`direct_motion`).

    The sample is divided by p(x^B)·p(ω) with p(ω) = p_light + p_dir for MIS, else the density of
    the technique that drew it (``densities`` = (p_light, p_dir)). ``light_point`` is the sampled
    emitter point (``None`` for the wedge technique, whose p_light is then evaluated from the
    traced source ray when MIS needs it).
    """
    p_light, p_dir = densities
    xB = dr.detach(edge.xB)
    ok = in_wedge(edge, w)
    # Source end: +ω reaches emission (for light sampling: exactly the sampled point)
    if light_point is None:
        d_src = w
    else:
        finite = dr.isfinite(light_point.x)
        d_src = dr.select(finite, normalize(light_point - origin), w)
    siS = scene.ray_intersect(mi.Ray3f(origin, d_src), ok)
    if light_point is not None:
        tS = dr.norm(siS.p - xB)
        ok &= dr.select(dr.isfinite(light_point.x),
                        siS.is_valid() & (dr.norm(siS.p - light_point) < 1e-4 * tS), ~siS.is_valid())
    Le = siS.emitter(scene).eval(siS, ok)
    ok &= dr.max(Le) > 0
    if mis and p_light is None:
        p_light = emitter_pdf(scene, xB, siS, ok)
    p_w = p_light + p_dir if mis else (p_dir if light_point is None else p_light)
    # Detector end: −ω hits a surface that the camera sees
    siD = scene.ray_intersect(mi.Ray3f(origin, -w), ok)
    ok &= siD.is_valid()
    xD = dr.select(ok, siD.p, xB - w)  # finite dummy on rejected lanes keeps NaNs out of AD
    # Camera connection at x^D: light arrives along ω (from x^B), leaves towards the camera
    importance_fs, uv, pixel, ok, _ = connect_camera(scene, camera, xD, w, ok)
    G = importance_fs * Le / (edge.pdf * p_w)
    exw = dr.cross(edge.e, w)
    sin_phi = dr.norm(exw)
    sigma = dr.sign(dr.dot(exw, edge.p2 - edge.p0))
    tD = dr.norm(xB - xD)
    coef = dr.select(ok, G * (tD * sin_phi * sigma), 0.0)
    env = ~siS.is_valid()
    tS = dr.norm(siS.p - xB)
    lever = dr.select(env | ~ok, 1.0, tS / dr.maximum(tS + tD, 1e-30))
    return coef, exw / sin_phi, uv, pixel, ok, xD, env, lever


def is_infinite(ds: mi.DirectionSample3f):
    """Whether a direction sample comes from an environment emitter (envmap, sky, constant).

    The emitter flag decides, not ``ds.dist``: ``sunsky`` reports a finite distance."""
    return mi.has_flag(ds.emitter.flags(), mi.EmitterFlags.Infinite) | dr.isinf(ds.dist)


def sample_light(scene: mi.Scene, xB, u):
    """``light`` technique: ω towards a sampled emitter point (or environment direction) and p(ω)."""
    it = dr.zeros(mi.Interaction3f)
    it.p = xB
    ds, _ = scene.sample_emitter_direction(it, u, False)
    point = dr.select(is_infinite(ds), mi.Point3f(dr.inf), ds.p)
    return ds.d, ds.pdf, point


def direct_segments(scene: mi.Scene, camera, draw: EdgeDraw, technique: str, u, *, mis: bool):
    """Detached boundary segments of one technique from primary samples ``u`` = (u1, u2) on the
    edges ``draw``.

    Returns (edge, ω, coef, m̂, film uv, pixel, mask, x^D, env, λ): ``coef`` is the u-space
    integrand without the velocity, G·t_D·sinφ·σ (see :func:`segment_weight`); ``edge.xB`` keeps
    its AD dependence on ``draw.P``; ``camera`` is a :class:`.camera.SensorCamera` or
    :class:`.camera.LaneCameras`."""
    u1, u2 = u
    edge = sample_edge_point(draw.edges, draw.P, draw.distr, u1)
    with dr.suspend_grad():
        xB = dr.detach(edge.xB)
        origin = ray_origin(edge)
        if technique == "light":
            w, p_light, point = sample_light(scene, xB, u2)
            p_dir = pdf_wedge(edge)
        else:
            (w, p_dir), p_light, point = sample_wedge(edge, u2), None, None
        coef, mhat, uv, pixel, ok, xD, env, lever = segment_weight(scene, camera, edge, w, (p_light, p_dir),
                                                                   origin, point, mis=mis)
    return edge, w, coef, mhat, uv, pixel, ok, xD, env, lever


def direct_target(scene: mi.Scene, sensors, draw: EdgeDraw, technique: str, u, *, mis: bool):
    """Guide target F̃(u) = Σ_views max_RGB |coef| for primary samples u (mi.Point3f)."""
    with dr.suspend_grad():
        total = mi.Float(0.0)
        for sensor in sensors:
            coef = direct_segments(scene, SensorCamera(sensor, *sensor.film().size()), draw, technique,
                                   (u.x, mi.Point2f(u.y, u.z)), mis=mis)[2]
            total += dr.max(dr.abs(coef))
        return total


def direct_motion(scene: mi.Scene, camera, draw: EdgeDraw, technique: str, u, weight, env_motion, *, mis: bool):
    """(v, pixel, mask, F̃) of samples ``u`` = (u1, u2): v = weight · coef · (m̂ · ω(θ)) (AD through
    ``draw.P`` and x^D(θ)); its derivative dv/dθ is the sample's contribution to dI/dθ.
    F̃ = max_RGB |coef| (detached, 0 where masked) is the guide target at the samples
    (:func:`direct_target`).

    ω(θ) = normalize(x^B(θ) − x^D_λ(θ)) with x^D_λ = x^D + λ (x^D(θ) − x^D), λ = t_S/(t_S + t_D):
    the source point x^S is fixed, so a moving x^D turns the segment x^D → x^S about x^S and
    moves it at the edge by only λ ẋ^D (m̂·ω̇ = m̂·(ẋ^B − λ ẋ^D)/t_D, the static-source case of
    the indirect term's m̂·(u̇2 − ẋ^S)); λ = 1 for the environment."""
    edge, w, coef, mhat, uv, pixel, ok, xD, env, lever = direct_segments(scene, camera, draw, technique, u, mis=mis)
    with dr.suspend_grad():
        size = dr.select(ok, dr.max(dr.abs(coef)), 0.0)
        coef *= weight
        dr.eval(coef, mhat, uv, pixel, ok, xD, env, lever, size)  # evaluate once: forward mode would re-trace otherwise
    # x^D(θ): the camera ray through the (fixed) film position, differentiable hit
    ray = camera(uv, ok)
    xD_t = dr.select(ok, scene.ray_intersect(ray, ok).p, xD)
    xD_t = dr.detach(xD_t) + lever * (xD_t - dr.detach(xD_t))
    rel = normalize(edge.xB - xD_t)
    if env_motion is not None:  # a rotating environment moves the source end of the segment
        rel = rel - dr.select(env, turn(env_motion, w), mi.Vector3f(0.0))
    return coef * dr.dot(mhat, rel), pixel, ok, size


def direct_motion_target(scene: mi.Scene, sensors, draw: EdgeDraw, technique: str, u, *, mis: bool):
    """[v per view] of :func:`direct_motion` at primary samples u (mi.Point3f), weight 1: with θ's
    gradient propagated, Σ_views max_RGB |dv/dθ| is the guide target including the velocity."""
    env_motion = environment_motion(scene)
    return [direct_motion(scene, SensorCamera(sensor, *sensor.film().size()), draw, technique,
                          (u.x, mi.Point2f(u.y, u.z)), 1.0, env_motion, mis=mis)[0] for sensor in sensors]


def direct_boundary(scene: mi.Scene, sensor: mi.Sensor, edges: BoundaryEdges, P, n_samples: int,
                    sampler: mi.Sampler, *, technique: str = "mis", guides=None):
    """Direct boundary contribution (flat W·H·3 image whose primal value is 0) from ``n_samples``
    samples (pairs for MIS); ``P`` is the AD vertex buffer of the edge objects. ``guides`` maps a
    technique (``light``/``dir``) to a guide over its primary samples (None: uniform); a
    :class:`~.sample_log.SampleLog` also keeps the samples for the next guide."""
    width, height = sensor.film().size()
    lanes = ViewLanes(SensorCamera(sensor, width, height), None, 1)
    return direct_image(scene, lanes, edges, P, n_samples, sampler, technique, guides=guides)


def views_direct_boundary(scene: mi.Scene, sensors, edges: BoundaryEdges, P, n_samples: int, sampler: mi.Sampler,
                          *, technique: str = "mis") -> list:
    """:func:`direct_boundary` of several views (one film size, unguided) traced as one wavefront:
    lane i (``n_samples`` per view, ``sampler`` as wide as all of them) belongs to view
    i // n_samples of ``sensors`` and connects to that view's camera (:class:`.camera.LaneCameras`);
    one image per view."""
    view, cameras = lane_views(sensors, n_samples)
    img = direct_image(scene, ViewLanes(cameras, view, len(sensors)), edges, P, n_samples, sampler, technique)
    return split_views(img, len(sensors))


def direct_image(scene: mi.Scene, lanes: ViewLanes, edges: BoundaryEdges, P, n_samples: int, sampler: mi.Sampler,
                 technique: str, *, guides=None, distr=None) -> mi.Float:
    """The direct boundary contributions of ``lanes.count`` views as one flat image, view-major
    (count·W·H·3), each lane's sample added to its view's part (:func:`direct_samples`)."""
    camera = lanes.camera
    img = dr.zeros(mi.Float, camera.width * camera.height * 3 * lanes.count)
    for v, pixel, ok in direct_samples(scene, lanes, edges, P, n_samples, sampler, technique, guides=guides,
                                       distr=distr):
        for c in range(3):
            dr.scatter_reduce(dr.ReduceOp.Add, img, v[c], pixel * 3 + c, ok)
    return img


def direct_samples(scene: mi.Scene, lanes: ViewLanes, edges: BoundaryEdges, P, n_samples: int, sampler: mi.Sampler,
                   technique: str, *, guides=None, distr=None) -> list:
    """Each technique's (v − detach(v), pixel, mask) per lane, v from :func:`direct_motion` with
    weight W·H / N and the pixel in its view's part of the views' joined image (``lanes.view``:
    each lane's view, None for one view); none without edges. ``distr``: the edges' length
    distribution (default: :func:`.boundary_sampling.edge_distribution`)."""
    camera, view = lanes.camera, lanes.view
    width, height = camera.width, camera.height
    if edges.count == 0:
        return []
    draw = edge_draw(edges, P) if distr is None else EdgeDraw(edges, P, distr)
    env_motion = environment_motion(scene)
    scale = dr.opaque(mi.Float, (width * height) / n_samples)
    out = []
    for t in (("light", "dir") if technique == "mis" else (technique,)):
        u1, u2, g = primary_sample(sampler, (guides or {}).get(t))
        if isinstance(guides, SampleLog):
            dr.eval(u1, u2, g)  # kept: read once by the kernels below and by the log
        v, pixel, ok, size = direct_motion(scene, camera, draw, t, (u1, u2), dr.detach(scale / g), env_motion,
                                           mis=technique == "mis")
        if isinstance(guides, SampleLog):
            guides.record(t, u1, u2, size, g)
        if view is not None:
            pixel += view * (width * height)
        out.append((v - dr.detach(v), pixel, ok))
    return out


def estimate(scene, edges: BoundaryEdges, view: int, spp: int, seed: int, estimator, max_depth: int, *,
             guide=None) -> mi.Float:
    """One pass of the direct term (:class:`~.term.Term` signature) with ``estimator.sampling``;
    ``guide`` maps a technique to its guide."""
    n, sampler, P = boundary_pass(scene, edges, spp, seed)
    return direct_boundary(scene.mi_scene, scene.sensors[view], edges, P, n, sampler, technique=estimator.sampling,
                           guides=guide)


def estimate_views(scene, edges: BoundaryEdges, views, spp: int, seed: int, estimator, max_depth: int) -> list:
    """One unguided pass of the direct term for several ``views`` traced as one wavefront (the
    samples of :func:`estimate`, drawn from one sampler seeded with ``seed``): a flat W·H·3 AD
    image per view."""
    n, sampler, P = boundary_pass(scene, edges, spp, seed, len(views))
    return views_direct_boundary(scene.mi_scene, [scene.sensors[v] for v in views], edges, P, n, sampler,
                                 technique=estimator.sampling)


def guide_techniques(sampling: str) -> tuple:
    """The techniques with a guide each: light and dir under MIS, else the one sampled."""
    return ("light", "dir") if sampling == "mis" else (sampling,)


def guide_target(scene: mi.Scene, sensors, draw: EdgeDraw, technique: str, u, sampler, max_depth: int, *,
                 mis: bool) -> mi.Float:
    """:func:`direct_target` as a :class:`~.term.GuideTarget` evaluates it (no sampler, any depth)."""
    return direct_target(scene, sensors, draw, technique, u, mis=mis)


TERM = Term("direct", samples_key="boundary_spp", stream=3, estimate=estimate,
            guide=GuideTarget(guide_techniques, guide_target, motion=direct_motion_target, loop_fed=True),
            estimate_views=estimate_views)
