"""Indirect boundary term: general boundary segments (x^D ← x^B → x^S) with subpaths on both ends.

The mathematics is docs/theory.md §3 ("Indirect term"). The ``dir`` technique draws (x^B, ω)
(§2); a source subpath path-traced along +ω gives the radiances S_k (k further segments after
x^S) and a light-tracing walk from x^D gives the camera importances D_j (j segments back to the
camera). Every split with j + 1 + k ≤ max_depth except (j, k) = (1, 0), the direct term's,
contributes, for a surface source,

    F_j = D_j · Σ_k S_k / (p(x^B) p(ω)),   v = F_j · sinφ · σ · (t_D/dist) · m̂ · (u2(θ) − x^S(θ)),

u2 being where the line from x^D(θ) through x^B(θ) meets the source triangle's plane (for the
environment v = F_j · sinφ · σ · t_D · m̂ · ω(θ)). Why this is the normal velocity of the
visibility boundary, and where x^D(θ) is tied (to the pixel for j = 1, a material point for
j ≥ 2), is in §3; guided sampling is §5.

Parameters (experiment keys)
----------------------------
``estimator.terms`` (list of term names, default all four)
    The term runs when ``indirect`` is listed.
``estimator.boundary_spp`` (int ≥ 1, default 16)
    Boundary segments per pixel of each view, one subpath pair each.
``scene.max_depth`` (int ≥ 1, default 2)
    Longest path in segments; the term needs at least 3 and is zero below that.
``estimator.guiding`` (``auto`` | ``none`` | ``grid`` | ``kdtree``, default ``auto``)
    Guide of the ``dir`` samples (§5; ``auto``: :mod:`psdr_cli.guiding.auto`); its target holds
    one random subpath pair per evaluation.
``estimator.guide_epsilon`` (float in [0, 1], default 0.05)
    Uniform share ε of the guide.
``estimator.kdtree.*``, ``estimator.grid.*``
    Build parameters of the guide (:mod:`psdr_cli.guiding.kdtree`, :mod:`psdr_cli.guiding.grid`).
``estimator.edge_sort`` (bool, default false)
    Order the edges into chains (:mod:`.boundary_sampling`, §5).
``estimator.passes`` (int ≥ 1, default 1)
    Fewest passes each view's samples are split into (more when a pass would exceed
    :data:`.passes.AD_LANES` lanes).

``estimator.sampling`` is not read: the term always uses the ``dir`` technique.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from . import interior
from .interior import environment_motion, split_views, turn
from .boundary_sampling import (BoundaryEdges, EdgeDraw, edge_draw, in_wedge, normalize, primary_sample,
                                ray_origin, sample_edge_point, sample_wedge)
from .camera import SensorCamera, ViewLanes, connect_camera, lane_views
from .term import GuideTarget, Term, boundary_pass

FOLLOW = mi.RayFlags.All | mi.RayFlags.FollowShape
#: Shortest path (segments) with an indirect boundary segment: the term is 0 below it.
MIN_DEPTH = 3


def detector_walk(scene, camera, siD, w, depth: int, sampler, active):
    """Light-tracing walk from x^D for light arriving from x^B along −ω (``w`` = +ω), connected to
    ``camera`` (:class:`.camera.SensorCamera`, or :class:`.camera.LaneCameras`: each lane's own).

    Returns a list over j = 1..depth of (D_j, film position, pixel, mask)."""
    out = []
    ctx = mi.BSDFContext(mi.TransportMode.Importance)
    si, w_in, beta, active = mi.SurfaceInteraction3f(siD), w, mi.Color3f(1.0), mi.Bool(active)  # copies: the caller's stay intact
    for j in range(1, depth + 1):
        value, uv, pixel, ok, _ = connect_camera(scene, camera, si.p, w_in, active)
        out.append((beta * value, uv, pixel, ok))
        if j == depth:
            break
        si.wi = si.to_local(w_in)
        bs, weight = si.bsdf().sample(ctx, si, sampler.next_1d(), sampler.next_2d(), active)
        d = si.to_world(bs.wo)
        beta *= weight
        active &= (bs.pdf > 0) & (dr.max(beta) > 0)
        si = scene.ray_intersect(si.spawn_ray(d), active)
        active &= si.is_valid()
        w_in = -d
    return out


def boundary_motion(xB, xD, siS_ad, source_surface, coef_geometry, mhat, *, env_motion, w_sample):
    """m̂·(motion of the visibility boundary) scaled as in the module docstring (AD, primal ≠ 0).

    ``coef_geometry`` holds the detached factor sinφ·σ·t_D (the 1/dist factor is added here).
    For an environment source that rotates (``env_motion``), m̂·ω(θ) becomes m̂·(ω(θ) − ω_src(θ))
    with ω_src the environment's material direction of the sampled ``w_sample``
    (see :func:`interior.environment_motion`)."""
    w = normalize(xB - xD)
    w_src = turn(env_motion, w_sample)  # a rotating environment moves the source end
    env = coef_geometry * dr.dot(mhat, w if env_motion is None else w - w_src)
    # Lanes without a source surface get a harmless stand-in (no NaN may enter the AD graph)
    xS = dr.select(source_surface, siS_ad.p, xB + w)
    nS = dr.select(source_surface, siS_ad.n, w)
    denom = dr.dot(xB - xD, nS)
    t = dr.dot(xS - xD, nS) / dr.select(denom != 0, denom, 1.0)
    u2 = xD + t * (xB - xD)
    dist = dr.detach(dr.norm(xS - xD))
    surface = coef_geometry / dr.maximum(dist, 1e-12) * dr.dot(mhat, u2 - xS)
    return dr.select(source_surface, surface, env)


def indirect_segments(scene, camera, draw: EdgeDraw, u, sampler, max_depth: int):
    """Detached segments from primary samples ``u`` = (u1, u2) on the edges ``draw`` with both
    subpaths, the detector's walk connected to ``camera`` (:func:`detector_walk`).

    Returns (edge, ω, geometry, m̂, S, walk, siS, siD, mask): ``geometry`` = sinφ·σ·t_D/(p(x^B)p(ω)),
    ``S[k]`` the source radiances, ``walk`` the detector terms (see :func:`detector_walk`)."""
    u1, u2 = u
    edge = sample_edge_point(draw.edges, draw.P, draw.distr, u1)
    with dr.suspend_grad():
        xB = dr.detach(edge.xB)
        origin = ray_origin(edge)
        w, p_dir = sample_wedge(edge, u2)
        ok = in_wedge(edge, w)
        siD = scene.ray_intersect(mi.Ray3f(origin, -w), ok)
        ok &= siD.is_valid()
        # Source subpath: S[k] = radiance through x^S with k further segments
        S = interior.radiance(scene, sampler, mi.Ray3f(origin, w), max_depth - 1, ok, by_depth=True)
        siS = scene.ray_intersect(mi.Ray3f(origin, w), ok)
        exw = dr.cross(edge.e, w)
        sin_phi = dr.norm(exw)
        mhat = exw / sin_phi
        sigma = dr.sign(dr.dot(exw, edge.p2 - edge.p0))
        tD = dr.norm(xB - siD.p)
        geometry = dr.select(ok, sin_phi * sigma * tD / (edge.pdf * p_dir), 0.0)
        walk = detector_walk(scene, camera, siD, w, max_depth - 1, sampler, ok)
    return edge, w, geometry, mhat, S, walk, siS, siD, ok


def path_weight(S, D, ok_j, j: int, max_depth: int):
    """F_j = D_j · Σ_k S_k over the source lengths k that complete a path of ≤ max_depth
    segments (k ≥ 1 when j = 1: the (1, 0) split belongs to the direct term)."""
    Ssum = mi.Color3f(0.0)
    for k in range(1 if j == 1 else 0, max_depth - 1 - j + 1):
        Ssum += S[k]
    return dr.select(ok_j, D * Ssum, 0.0)


def indirect_target(scene, sensors, draw: EdgeDraw, sampler, max_depth: int, u):
    """Guide target F̃(u) = Σ_views Σ_j max_RGB |F_j · geometry| (one random subpath pair)."""
    with dr.suspend_grad():
        total = mi.Float(0.0)
        for sensor in sensors:
            _, _, geometry, _, S, walk, _, _, _ = indirect_segments(
                scene, SensorCamera(sensor, *sensor.film().size()), draw, (u.x, mi.Point2f(u.y, u.z)), sampler,
                max_depth)
            for j, (D, _, _, ok_j) in enumerate(walk, start=1):
                if max_depth - 1 - j < 0:
                    break
                total += dr.max(dr.abs(path_weight(S, D, ok_j, j, max_depth) * geometry))
        return total


def indirect_boundary(scene: mi.Scene, sensor: mi.Sensor, edges: BoundaryEdges, P, n_samples: int,
                      sampler: mi.Sampler, max_depth: int, *, guide=None):
    """Indirect boundary contribution (flat W·H·3 image, primal 0) from ``n_samples`` segments,
    with primary samples from ``guide`` when given (divided by its density)."""
    width, height = sensor.film().size()
    lanes = ViewLanes(SensorCamera(sensor, width, height), None, 1)
    return indirect_image(scene, lanes, edges, P, n_samples, sampler, max_depth, guide=guide)


def views_indirect_boundary(scene: mi.Scene, sensors, edges: BoundaryEdges, P, n_samples: int, sampler: mi.Sampler,
                            max_depth: int) -> list:
    """:func:`indirect_boundary` of several views (one film size, unguided) traced as one wavefront:
    lane i (``n_samples`` per view, ``sampler`` as wide as all of them) belongs to view
    i // n_samples of ``sensors`` and its detector walk connects to that view's camera
    (:class:`.camera.LaneCameras`); one image per view."""
    view, cameras = lane_views(sensors, n_samples)
    img = indirect_image(scene, ViewLanes(cameras, view, len(sensors)), edges, P, n_samples, sampler, max_depth)
    return split_views(img, len(sensors))


def indirect_image(scene: mi.Scene, lanes: ViewLanes, edges: BoundaryEdges, P, n_samples: int,
                   sampler: mi.Sampler, max_depth: int, *, guide=None) -> mi.Float:
    """The indirect boundary contributions of ``lanes.count`` views as one flat image, view-major
    (count·W·H·3), each lane's segment added to its view's part (:func:`indirect_samples`), from
    ``n_samples`` segments per view."""
    camera = lanes.camera
    img = dr.zeros(mi.Float, camera.width * camera.height * 3 * lanes.count)
    for v, pixel, live in indirect_samples(scene, lanes, edges, P, n_samples, sampler, max_depth, guide=guide):
        for c in range(3):
            dr.scatter_reduce(dr.ReduceOp.Add, img, v[c], pixel * 3 + c, live)
    return img


def indirect_samples(scene: mi.Scene, lanes: ViewLanes, edges: BoundaryEdges, P, n_samples: int,
                     sampler: mi.Sampler, max_depth: int, *, guide=None, distr=None) -> list:
    """Per detector length j = 1…max_depth − 2, each lane's (v − detach(v), pixel, mask): v of the
    module docstring with weight W·H / (N·g(u)) (``n_samples`` = N segments per view, g the
    guide's density, 1 unguided), the pixel in its view's part of the views' joined image
    (``lanes.view``: each lane's view, None for one view); none without edges or below depth 3
    (a path with a boundary segment and ≥ 3 segments is needed). ``distr``: the edges' length
    distribution (default: :func:`.boundary_sampling.edge_distribution`)."""
    camera, view = lanes.camera, lanes.view
    width, height = camera.width, camera.height
    if edges.count == 0 or max_depth < MIN_DEPTH:
        return []
    draw = edge_draw(edges, P) if distr is None else EdgeDraw(edges, P, distr)
    u1, u2, g = primary_sample(sampler, guide)
    edge, w, geometry, mhat, S, walk, siS, siD, ok = indirect_segments(scene, camera, draw, (u1, u2), sampler,
                                                                       max_depth)
    with dr.suspend_grad():
        geometry *= dr.opaque(mi.Float, (width * height) / n_samples) / g
        dr.eval(S, walk, geometry, mhat, siS, siD)
    origin = ray_origin(edge)
    # Moving end points (AD): the source material point, x^D as a material point (j ≥ 2)
    siS_ad = scene.ray_intersect(mi.Ray3f(origin, w), FOLLOW, False, ok & siS.is_valid())
    siD_ad = scene.ray_intersect(mi.Ray3f(origin, -w), FOLLOW, False, ok)
    surface = siS.is_valid()
    env_motion = environment_motion(scene)
    out = []
    for j, (D, uv, pixel, ok_j) in enumerate(walk, start=1):
        if max_depth - 1 - j < 0:
            break
        with dr.suspend_grad():
            F = path_weight(S, D, ok_j, j, max_depth)
            live = ok_j & (dr.max(F) > 0)
        if j == 1:  # camera vertex: x^D slides along the camera ray through its film position
            xD_t = dr.select(live, scene.ray_intersect(camera(uv, live), live).p, siD.p)
        else:
            xD_t = siD_ad.p
        v = F * boundary_motion(edge.xB, xD_t, siS_ad, surface, geometry, mhat, env_motion=env_motion, w_sample=w)
        v = dr.select(live, v - dr.detach(v), 0.0)
        if view is not None:
            pixel = pixel + view * (width * height)
        out.append((v, pixel, live))
    return out


def estimate(scene, edges: BoundaryEdges, view: int, spp: int, seed: int, estimator, max_depth: int, *,
             guide=None) -> mi.Float:
    """One pass of the indirect term (:class:`~.term.Term` signature)."""
    n, sampler, P = boundary_pass(scene, edges, spp, seed)
    return indirect_boundary(scene.mi_scene, scene.sensors[view], edges, P, n, sampler, max_depth, guide=guide)


def estimate_views(scene, edges: BoundaryEdges, views, spp: int, seed: int, estimator, max_depth: int) -> list:
    """One unguided pass of the indirect term for several ``views`` traced as one wavefront (the
    samples of :func:`estimate`, drawn from one sampler seeded with ``seed``): a flat W·H·3 AD
    image per view."""
    n, sampler, P = boundary_pass(scene, edges, spp, seed, len(views))
    return views_indirect_boundary(scene.mi_scene, [scene.sensors[v] for v in views], edges, P, n, sampler, max_depth)


def guide_techniques(sampling: str) -> tuple:
    """One guide, of the direction technique ``dir`` (the term samples the segment's direction at the
    edge point: no light sampling, no MIS)."""
    return ("dir",)


def guide_target(scene: mi.Scene, sensors, draw: EdgeDraw, technique: str, u, sampler, max_depth: int, *,
                 mis: bool) -> mi.Float:
    """:func:`indirect_target` as a :class:`~.term.GuideTarget` evaluates it (one random subpath
    pair per sample; the technique and MIS do not apply)."""
    return indirect_target(scene, sensors, draw, sampler, max_depth, u)


TERM = Term("indirect", samples_key="boundary_spp", stream=4, estimate=estimate,
            guide=GuideTarget(guide_techniques, guide_target, seed_offset=2, min_depth=MIN_DEPTH, random=True,
                              per_technique=False),
            estimate_views=estimate_views)
