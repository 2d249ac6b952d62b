"""Primary boundary term: discontinuities of the image integrand along projected edges.

With the camera vertex tied to the pixel, the pixel integral I = ∫_pixel L(q) dq (q in pixels)
changes only where the integrand jumps across a moving curve: the projected silhouette edges of
the moving meshes (and, for flat-shaded meshes, every non-flat edge, across which the shading
normal jumps). For a projected edge point q(θ) with screen normal n_s,

    dI/dθ = ∫_edges (n_s · q̇) [L(q − ε n_s) − L(q + ε n_s)] dl.

Sampling: an edge ∝ its projected length, a uniform point on it, p(q) = 1/Σℓ (pixels). Each
sample adds (1/N)·[(n_s·q(θ)) ΔL / p(q) − detach(·)] to the pixel of q.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from . import interior
from .boundary_sampling import BoundaryEdges
from .camera import Projection, camera_ray, film_pixel

#: Offset of the two radiance samples from the edge, in pixels.
SIDE_EPS = 1e-3


def primary_edge_ids(edges: BoundaryEdges, V: np.ndarray, camera_origin):
    """(v0, v1) vertex ids of the edges that can carry an image discontinuity for this camera.

    Smooth-shaded meshes: silhouette and open edges; flat-shaded meshes: every non-flat edge."""
    v0, v1 = [], []
    for topo, offset, smooth in edges.meshes:
        Vo = V[offset: offset + int(topo.faces.max()) + 1]
        sel = topo.primary(Vo, camera_origin) if smooth else np.nonzero(~topo.flat)[0]
        v0.append(topo.v0[sel] + offset)
        v1.append(topo.v1[sel] + offset)
    if not v0:
        return np.zeros(0, np.uint32), np.zeros(0, np.uint32)
    return np.concatenate(v0).astype(np.uint32), np.concatenate(v1).astype(np.uint32)


def edge_depth(ray, p0, p1):
    """Distance along ``ray`` to the point of the line p0p1 closest to it (the edge under q)."""
    e = p1 - p0
    w = ray.o - p0
    b = dr.dot(ray.d, e)
    c = dr.squared_norm(e)
    denom = c - b * b  # ray.d is unit length
    return (b * dr.dot(w, e) - c * dr.dot(ray.d, w)) / dr.select(denom > 0, denom, 1.0)


def edge_visible(scene, rays, p0, p1, active):
    """Whether the edge point under q is seen by the camera: on at least one side of the edge the
    first hit is not in front of the edge (otherwise an occluder covers it, and a discontinuity
    seen there belongs to another edge that projects onto the same line)."""
    t_edge = edge_depth(rays[0], p0, p1)
    seen = mi.Bool(False)
    for ray in rays:
        si = scene.ray_intersect(ray, active)
        seen |= ~si.is_valid() | (si.t > t_edge * (1.0 - 1e-3))
    return active & seen


def primary_boundary(scene: mi.Scene, sensor: mi.Sensor, edges: BoundaryEdges, P, n_samples: int,
                     sampler: mi.Sampler, max_depth: int):
    """Primary boundary contribution (flat W·H·3 image, primal 0) from ``n_samples`` edge points."""
    proj = Projection(sensor)
    width, height = proj.width, proj.height
    img = dr.zeros(mi.Float, width * height * 3)
    if edges.count == 0:
        return img
    V = np.asarray(dr.detach(P), np.float64).reshape(-1, 3)
    ids0, ids1 = primary_edge_ids(edges, V, np.asarray(proj.origin, np.float64).reshape(-1)[:3])
    if len(ids0) == 0:
        return img
    q0, z0 = proj(dr.gather(mi.Point3f, P, mi.UInt32(ids0)))
    q1, z1 = proj(dr.gather(mi.Point3f, P, mi.UInt32(ids1)))
    with dr.suspend_grad():
        front = (dr.detach(z0) > proj.near) & (dr.detach(z1) > proj.near)
        length = dr.select(front, dr.norm(dr.detach(q1 - q0)), 0.0)
        total = float(dr.sum(length)[0])
    if not total > 0:
        return img
    distr = mi.DiscreteDistribution(length)
    k, s = distr.sample_reuse(sampler.next_1d())
    qa, qb = dr.gather(mi.Point2f, q0, k), dr.gather(mi.Point2f, q1, k)
    q = qa + s * (qb - qa)
    with dr.suspend_grad():
        qd = dr.detach(q)
        t = dr.normalize(dr.detach(qb - qa))
        n_s = mi.Vector2f(-t.y, t.x)
        ok = (qd.x >= 0) & (qd.x < width) & (qd.y >= 0) & (qd.y < height)
        rays = [camera_ray(sensor, qd + sign * SIDE_EPS * n_s, width, height, ok) for sign in (-1.0, 1.0)]
        ok &= edge_visible(scene, rays, dr.gather(mi.Point3f, dr.detach(P), dr.gather(mi.UInt32, mi.UInt32(ids0), k)),
                           dr.gather(mi.Point3f, dr.detach(P), dr.gather(mi.UInt32, mi.UInt32(ids1), k)), ok)
        sides = [interior.radiance(scene, sampler, ray, max_depth, ok) for ray in rays]
        # opaque: the edge length sum changes with the geometry and must not be baked into the kernel
        delta = dr.select(ok, (sides[0] - sides[1]) * dr.opaque(mi.Float, total / n_samples), 0.0)
        pixel = dr.select(ok, film_pixel(qd, width), 0)
        dr.eval(delta, pixel, n_s, ok)
    v = delta * dr.dot(n_s, q)
    v = v - dr.detach(v)
    for c in range(3):
        dr.scatter_reduce(dr.ReduceOp.Add, img, v[c], pixel * 3 + c, ok)
    return img
