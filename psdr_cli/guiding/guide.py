"""The guide interface: a density g(u) on the boundary primary-sample space u ∈ [0,1)³.

Every guide here is a partition of [0,1)³ into axis-aligned boxes ("leaves"), each carrying a
non-negative trilinear function given by its 8 corner values c_ijk (i, j, k ∈ {0,1} along
u1, u2.x, u2.y). With x ∈ [0,1)³ the position inside the leaf,

    f(u) = Σ_ijk c_ijk · (i ? x1 : 1−x1)(j ? x2 : 1−x2)(k ? x3 : 1−x3),
    mass_leaf = volume · mean(c),   M = Σ mass_leaf,
    g(u) = ε + (1 − ε) · f(u) / M.

The uniform share ε keeps every estimator unbiased where the guide missed a region. Because a
constant plus a trilinear function is trilinear, g itself is trilinear in every leaf, with
corners c'_ijk = ε + (1 − ε) c_ijk / M; sampling needs no separate uniform branch and no
lookup: a leaf is chosen ∝ volume · mean(c'), then x is drawn by inverting x3's marginal, then
x2 | x3, then x1 | x2, x3 — each is linear, (1−t)a + t b, with the closed-form inverse
t = ξ(a + b) / (a + √(a² + ξ(b² − a²))), and g(u) is c' interpolated at x. A grid is the special
case of equal corner values on a regular partition; the Kd-tree stores its split planes for
lookups of g at arbitrary u (tests, plots).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import drjit as dr
import mitsuba as mi
import numpy as np

from ..support.jitarray import jit_array

#: corner index c = i + 2j + 4k ↔ offsets (i, j, k)
CORNERS = np.array([[c & 1, (c >> 1) & 1, (c >> 2) & 1] for c in range(8)], np.float64)
#: largest float32 below 1 (samples stay inside [0,1))
ONE_MINUS = float(np.nextafter(np.float32(1.0), np.float32(0.0)))


@dataclass
class GuideStats:
    """What ``psdr guide-stats`` reports for one guide."""
    kind: str
    leaves: int = 0
    max_depth: int = 0
    memory_bytes: int = 0
    build_seconds: float = 0.0
    evaluations: int = 0
    normalization: float = 0.0
    intervals: int = 0
    extra: dict = field(default_factory=dict)


def trilinear_weights(x: np.ndarray) -> np.ndarray:
    """Weights (N, 8) of the corner values at local positions x (N, 3)."""
    return np.prod(np.where(CORNERS[None] > 0, x[:, None, :], 1.0 - x[:, None, :]), axis=2)


def invert_linear(a, b, xi):
    """t ∈ [0,1] with ∫₀ᵗ ((1−s)a + s b) ds = ξ (a + b)/2 (Dr.Jit, a, b ≥ 0)."""
    denom = a + dr.safe_sqrt(a * a + xi * (b * b - a * a))
    return dr.select(denom > 0, xi * (a + b) / dr.select(denom > 0, denom, 1.0), xi)


class Guide:
    """Trilinear leaves mixed with the uniform density; subclasses say how u finds its leaf."""

    kind = "guide"

    def __init__(self, lo: np.ndarray, hi: np.ndarray, corners: np.ndarray, epsilon: float,
                 stats: GuideStats):
        self.lo = np.asarray(lo, np.float64)
        self.hi = np.asarray(hi, np.float64)
        self.corners = np.maximum(np.asarray(corners, np.float64), 0.0)
        vol = np.prod(self.hi - self.lo, axis=1)
        self.mass = vol * self.corners.mean(axis=1)
        self.total = float(self.mass.sum())
        # Nothing to guide towards (e.g. no edge contributes): the guide is the uniform density.
        self.epsilon = float(epsilon) if self.total > 0 else 1.0
        self.stats = stats
        stats.leaves, stats.normalization = len(self.lo), self.total
        # g = ε + (1 − ε) f / M, trilinear per leaf with corners c'
        scale = 1.0 / self.total if self.total > 0 else 0.0
        self.density_corners = self.epsilon + (1.0 - self.epsilon) * self.corners * scale
        self.probability = vol * self.density_corners.mean(axis=1)  # sums to 1
        self._lo = jit_array(mi.Float, self.lo.ravel())
        self._ext = jit_array(mi.Float, (self.hi - self.lo).ravel())
        self._c = jit_array(mi.Float, self.density_corners.ravel())
        self._distr = mi.DiscreteDistribution(jit_array(mi.Float, self.probability))

    # -- lookups -------------------------------------------------------------------------------
    def leaf_of(self, u: mi.Point3f) -> mi.UInt32:
        """Index of the leaf containing u (Dr.Jit)."""
        raise NotImplementedError

    def leaf_of_np(self, u: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def memory_bytes(self) -> int:
        """Bytes of the arrays the sampler keeps (boxes, corner values, leaf CDF)."""
        return 4 * (len(self._lo) + len(self._ext) + len(self._c) + len(self.probability))

    # -- density -------------------------------------------------------------------------------
    def _leaf_density(self, leaf, x):
        """g(u) inside ``leaf`` at local position x (Dr.Jit)."""
        val = mi.Float(0.0)
        for c in range(8):
            w = ((x.x if c & 1 else 1.0 - x.x) * (x.y if c & 2 else 1.0 - x.y)
                 * (x.z if c & 4 else 1.0 - x.z))
            val += w * dr.gather(mi.Float, self._c, leaf * 8 + c)
        return val

    def pdf(self, u: mi.Point3f) -> mi.Float:
        """g(u) (Dr.Jit)."""
        leaf = self.leaf_of(u)
        lo = dr.gather(mi.Point3f, self._lo, leaf)
        ext = dr.gather(mi.Vector3f, self._ext, leaf)
        return self._leaf_density(leaf, (u - lo) / ext)

    def pdf_batch(self, u: np.ndarray) -> np.ndarray:
        """g(u) at numpy points u (N,3), evaluated by :meth:`pdf` (Dr.Jit)."""
        pt = mi.Point3f(*(jit_array(mi.Float, u[:, i]) for i in range(3)))
        return np.asarray(self.pdf(pt), np.float64)

    def pdf_np(self, u: np.ndarray) -> np.ndarray:
        """g(u) (numpy, for tests and plots)."""
        u = np.atleast_2d(np.asarray(u, np.float64))
        leaf = self.leaf_of_np(u)
        x = (u - self.lo[leaf]) / (self.hi[leaf] - self.lo[leaf])
        return np.einsum("nc,nc->n", trilinear_weights(x), self.density_corners[leaf])

    # -- sampling ------------------------------------------------------------------------------
    def sample(self, u_leaf: mi.Float, xi: mi.Point3f):
        """u ~ g from a uniform ``u_leaf`` (leaf choice) and ``xi`` ∈ [0,1)³. Returns (u, g(u))."""
        leaf = self._distr.sample(dr.clip(u_leaf, 0.0, ONE_MINUS))
        c = [dr.gather(mi.Float, self._c, leaf * 8 + k) for k in range(8)]
        # x3 from its marginal: corner sums over the faces x3 = 0 and x3 = 1
        z = invert_linear(c[0] + c[1] + c[2] + c[3], c[4] + c[5] + c[6] + c[7], xi.z)
        e = [dr.lerp(c[k], c[k + 4], z) for k in range(4)]          # bilinear slice at x3
        y = invert_linear(e[0] + e[1], e[2] + e[3], xi.y)
        x = invert_linear(dr.lerp(e[0], e[2], y), dr.lerp(e[1], e[3], y), xi.x)
        lo = dr.gather(mi.Point3f, self._lo, leaf)
        ext = dr.gather(mi.Vector3f, self._ext, leaf)
        u = dr.clip(lo + ext * mi.Point3f(x, y, z), 0.0, ONE_MINUS)
        density = dr.lerp(dr.lerp(e[0], e[1], x), dr.lerp(e[2], e[3], x), y)
        return u, density

    def sample_np(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """n samples u ~ g (numpy reference sampler used by tests)."""
        u = jit_array(mi.Float, rng.random(n))
        xi = mi.Point3f(*(jit_array(mi.Float, rng.random(n)) for _ in range(3)))
        s, p = self.sample(u, xi)
        return np.stack([np.asarray(s[i]) for i in range(3)], 1), np.asarray(p)


@dataclass(frozen=True)
class GuideKind:
    """A kind of guide (a word of ``estimator.guiding``): its name, how one is built, and whether
    the optimisation loop fits it to the samples its own passes kept (:mod:`.loop_fed`) instead of
    building it from target evaluations. Each guide module declares its ``KIND``
    (:mod:`.kinds` lists them):

        build(target, breaks, estimator, seed, pixels) -> Guide

    ``target`` maps numpy u (N, 3) to F̃ (N,), ``breaks`` are the u1 breakpoints of the edges,
    ``estimator`` the experiment's :class:`~psdr_cli.config.estimator_section.EstimatorConfig` (the
    kind's own keys), ``seed`` the build's seed and ``pixels`` the film's W·H."""
    name: str
    build: Callable[..., Guide]
    loop_fed: bool = False
