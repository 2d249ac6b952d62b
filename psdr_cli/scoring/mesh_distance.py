"""Distances between two triangle meshes: symmetric Chamfer and Hausdorff distances of point
samples. Reads and writes nothing.

Both meshes are normalised with the *reference's* bounding box (centre at the origin, longest
side 1), N points are drawn on each surface by area with a fixed seed, and with
d(p, Q) = min_q |p − q| (nearest sampled point, scipy's cKDTree):

    Chamfer-L1  = ½ (mean_{p∈P} d(p, Q) + mean_{q∈Q} d(q, P)),
    Chamfer-L2² = ½ (mean_{p∈P} d(p, Q)² + mean_{q∈Q} d(q, P)²),
    Hausdorff   = max(max_P d(p, Q), max_Q d(q, P)).

Point sampling puts a noise floor under these numbers: two independent samplings of the same
surface are on average ~0.5/√N·(area)^½ apart; :func:`noise_floor` measures it.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ..errors import PsdrError
from ..scene.meshes import face_areas


@dataclass
class Distance:
    chamfer_l1: float
    chamfer_l2: float
    hausdorff: float


def normalisation(V):
    """(centre, scale) mapping the bounding box of V to a box with longest side 1 at the origin."""
    lo, hi = V.min(0), V.max(0)
    return (lo + hi) / 2, 1.0 / max(float((hi - lo).max()), 1e-30)


def surface_points(V, F, n: int, seed: int):
    """n points uniformly distributed by area on the triangles (V, F)."""
    rng = np.random.default_rng(seed)
    area = face_areas(V, F)
    if not area.sum() > 0:
        raise PsdrError("mesh has zero surface area")
    tri = rng.choice(len(F), size=n, p=area / area.sum())
    r1, r2 = rng.random(n), rng.random(n)
    s = np.sqrt(r1)
    a, b, c = V[F[tri, 0]], V[F[tri, 1]], V[F[tri, 2]]
    return (1 - s)[:, None] * a + (s * (1 - r2))[:, None] * b + (s * r2)[:, None] * c


def distance(mesh, reference, samples: int = 100_000, seed: int = 0) -> Distance:
    """Chamfer (L1, squared L2) and Hausdorff distance of ``mesh`` to ``reference`` (each (V, F)),
    both normalised with the reference's bounding box."""
    centre, scale = normalisation(reference[0])
    P = surface_points((mesh[0] - centre) * scale, mesh[1], samples, seed)
    Q = surface_points((reference[0] - centre) * scale, reference[1], samples, seed + 1)
    dp = cKDTree(Q).query(P, workers=-1)[0]
    dq = cKDTree(P).query(Q, workers=-1)[0]
    return Distance(0.5 * (dp.mean() + dq.mean()), 0.5 * ((dp ** 2).mean() + (dq ** 2).mean()),
                    float(max(dp.max(), dq.max())))


def noise_floor(reference, samples: int = 100_000, seed: int = 0) -> Distance:
    """The distance of the reference to itself with independent samplings."""
    return distance(reference, reference, samples, seed + 1000)
