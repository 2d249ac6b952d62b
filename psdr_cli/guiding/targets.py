"""Guide targets and the set of guides one gradient estimate uses.

The target of a guide is the boundary term's integrand in primary-sample space without the
velocity factor, F̃(u) = Σ_views max_RGB |F(u)| (docs/theory.md §5), evaluated by the estimator's own
code path (:func:`direct.direct_target`, :func:`indirect.indirect_target`) for the views the
guide serves. For the indirect term F̃ contains one random source and detector subpath per
evaluation, a noisy but unbiased stand-in for the photon-map estimate of the paper's Eq. 11.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import drjit as dr
import mitsuba as mi
import numpy as np

from ..estimators.direct import direct_target
from ..estimators.indirect import indirect_target
from ..estimators.passes import make_sampler
from .grid import build_grid
from .kdtree import build_kdtree

#: lanes per batched target evaluation
CHUNK = 1 << 19


def target_function(scene, edges, views: list, term: str, technique: str, mis: bool,
                    max_depth: int, seed: int):
    """numpy u (N,3) → F̃ (N,) for ``term`` (direct/indirect) and ``technique``."""
    sensors = [scene.sensors[v] for v in views]
    mi_scene = scene.mi_scene
    calls = [0]

    def evaluate(u: np.ndarray) -> np.ndarray:
        out = np.empty(len(u))
        P = dr.detach(edges.positions(mi.traverse(mi_scene)))
        for a in range(0, len(u), CHUNK):
            chunk = u[a:a + CHUNK].astype(np.float32)
            pt = mi.Point3f(*(mi.Float(np.ascontiguousarray(chunk[:, i])) for i in range(3)))
            if term == "direct":
                val = direct_target(mi_scene, sensors, edges, P, technique, mis, pt)
            else:
                calls[0] += 1
                sampler = make_sampler(seed * 7919 + calls[0], len(chunk))
                val = indirect_target(mi_scene, sensors, edges, P, sampler, max_depth, pt)
            out[a:a + len(chunk)] = np.asarray(val, np.float64)
        return np.where(np.isfinite(out), out, 0.0)

    return evaluate


@dataclass
class Guides:
    """The guides of one estimate: ``direct[technique]`` and ``indirect`` (None: unguided)."""
    direct: dict = field(default_factory=dict)
    indirect: object = None

    def all(self):
        """[(label, guide)] for reports."""
        out = [(f"direct/{t}", g) for t, g in self.direct.items()]
        return out + ([("indirect/dir", self.indirect)] if self.indirect is not None else [])


def build_guide(kind: str, target, breaks, estimator, seed: int):
    """One guide of ``kind`` (grid or kdtree) from the experiment's ``estimator`` settings."""
    if kind == "grid":
        g = estimator.grid
        return build_grid(target, g.resolution, g.samples_per_cell, estimator.guide_epsilon, seed)
    k = estimator.kdtree
    return build_kdtree(target, breaks, k.samples_per_node, k.threshold, k.max_depth, k.max_leaves,
                        estimator.guide_epsilon, seed, k.initial_samples, k.interval_share)


def build_guides(scene, edges, views: list, terms, sampling: str, max_depth: int, estimator,
                 seed: int = 0) -> Guides:
    """Guides for the direct and indirect terms among ``terms`` (``estimator.guiding`` ≠ none)."""
    guides = Guides()
    if estimator.guiding == "none" or edges.count == 0:
        return guides
    breaks = edges.breakpoints(dr.detach(edges.positions(mi.traverse(scene.mi_scene))))
    mis = sampling == "mis"
    if "direct" in terms:
        for i, t in enumerate(("light", "dir") if mis else (sampling,)):
            f = target_function(scene, edges, views, "direct", t, mis, max_depth, seed)
            guides.direct[t] = build_guide(estimator.guiding, f, breaks, estimator, seed + i)
    if "indirect" in terms and max_depth >= 3:
        f = target_function(scene, edges, views, "indirect", "dir", False, max_depth, seed)
        guides.indirect = build_guide(estimator.guiding, f, breaks, estimator, seed + 2)
    return guides
