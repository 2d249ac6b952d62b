"""The coverage image of an object in a view, with its derivative: the share of each pixel's
camera rays whose first hit is on the object,

    C(p) = ∫_pixel 1[ray(q) first hits the object] dq,

the quantity a mask (a photograph's alpha) measures. The indicator is constant on each side of
a silhouette, so C has no interior derivative: dC/dθ is the primary boundary term with the jump
ΔC = 1 − 0 across silhouette edges (:func:`.primary.primary_boundary` with ``coverage``; the
same edge sampling, film projection and side offsets as the radiance's, docs/theory.md §4). The
primal value is the mean of ``spp`` hit indicators per pixel.

Parameters (experiment keys)
----------------------------
``estimator.spp`` (hit samples per pixel) and ``estimator.primary_spp`` (silhouette samples per
pixel), as for the colour image.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from .camera import camera_rays
from .passes import make_sampler
from .primary import hits_shape, primary_boundary, shape_id
from .term import boundary_pass


def object_id(scene, name: str) -> int:
    """The Mitsuba registry id of the scene object ``name`` (:func:`.primary.shape_id`)."""
    shape = next((s for s in scene.mi_scene.shapes() if s.id() == name), None)
    if shape is None:
        raise ValueError(f"no shape {name!r} in the scene")
    return shape_id(shape)


def hit_share(scene, view: int, spp: int, seed: int, sid: int) -> mi.Float:
    """Mean of ``spp`` indicators per pixel that a camera ray's first hit is on the shape with
    registry id ``sid`` (flat W·H, no derivative)."""
    width, height = scene.resolution
    with dr.suspend_grad():
        sampler = make_sampler(seed, width * height * spp)
        ray, _ = camera_rays(scene.sensors[view], sampler, width, height, spp)
        hit = dr.select(hits_shape(scene.mi_scene.ray_intersect(ray), sid), 1.0, 0.0)
        dr.eval(hit)
        return dr.block_sum(hit, spp, mode="evaluated") / spp


def coverage_image(scene, edges, name: str, view: int, seeds: tuple, estimator, *, spp: int,
                   primary_spp: int) -> mi.Float:
    """C of the object ``name`` in ``view`` (flat W·H, AD): its hit share (``spp`` rays per pixel)
    plus the silhouettes' boundary term (``primary_spp`` samples per pixel, primal 0), from the
    random streams ``seeds`` = (hits, silhouettes)."""
    width, height = scene.resolution
    sid = object_id(scene, name)
    image = hit_share(scene, view, spp, seeds[0], sid)
    if edges is None or (edges.count == 0 and not edges.meshes):
        return image
    n, sampler, P = boundary_pass(scene, edges, primary_spp, seeds[1])
    boundary = primary_boundary(scene.mi_scene, scene.sensors[view], edges, P, n, sampler, 1,
                                sampling=estimator.primary_sampling, coverage=sid)
    return image + dr.gather(mi.Float, boundary, dr.arange(mi.UInt32, width * height) * 3)
