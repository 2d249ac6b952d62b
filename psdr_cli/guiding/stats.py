"""What ``psdr guide-stats`` measures: guide sizes and costs, edge chains, target along u1."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from ..estimators.boundary_sampling import edge_distribution, sample_edge_point
from .targets import build_guide, target_function


def chain_stats(edges) -> dict:
    """Edges, chains (continuous pieces of x^B(u1)) and mean chain length."""
    return {"edges": int(edges.count), "chains": int(edges.chains.count),
            "mean_chain_length": float(edges.chains.mean_length())}


def target_curve(scene, edges, views, technique: str, max_depth: int, n_u1: int = 2048,
                 n_u2: int = 16, seed: int = 0):
    """(u1, x^B(u1) (N,3), mean over u2 of F̃_technique (N,), breakpoints) for plots."""
    u1 = (np.arange(n_u1) + 0.5) / n_u1
    rng = np.random.default_rng(seed)
    u = np.concatenate([np.repeat(u1, n_u2)[:, None], rng.random((n_u1 * n_u2, 2))], axis=1)
    term = "indirect" if technique == "indirect" else "direct"
    f = target_function(scene, edges, views, term, "dir" if term == "indirect" else technique,
                        False, max_depth, seed)
    mean = f(u).reshape(n_u1, n_u2).mean(1)
    P = dr.detach(edges.positions(mi.traverse(scene.mi_scene)))
    with dr.suspend_grad():
        e = sample_edge_point(edges, P, edge_distribution(edges, P), mi.Float(u1.astype(np.float32)))
        xB = np.stack([np.asarray(e.xB[i], np.float64) for i in range(3)], 1)
    return u1, xB, mean, edges.breakpoints(P)


def guide_report(scene, edges, views, kinds, techniques, max_depth: int, estimator, seed: int = 0):
    """Build every (kind, technique) guide; returns ({label: GuideStats-dict}, {label: guide}).

    Targets use the MIS weights when ``estimator.sampling`` is ``mis`` (as the estimator does);
    kernels are compiled by a small warm-up call first, so build seconds are steady-state."""
    breaks = edges.breakpoints(dr.detach(edges.positions(mi.traverse(scene.mi_scene))))
    stats, guides = {}, {}
    for kind in kinds:
        for i, t in enumerate(techniques):
            term = "indirect" if t == "indirect" else "direct"
            f = target_function(scene, edges, views, term, "dir" if term == "indirect" else t,
                                term == "direct" and estimator.sampling == "mis", max_depth, seed)
            f(np.random.default_rng(0).random((1024, 3)))  # warm-up: compile the target's kernels
            g = build_guide(kind, f, breaks, estimator, seed + i)
            label = f"{kind}/{t}"
            s = g.stats
            stats[label] = {"guide": kind, "technique": t, "leaves": s.leaves, "max_depth": s.max_depth,
                            "memory_bytes": s.memory_bytes, "build_seconds": s.build_seconds,
                            "evaluations": s.evaluations, "normalization": s.normalization,
                            "u1_intervals": s.intervals}
            guides[label] = g
    return stats, guides
