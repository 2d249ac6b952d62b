"""Guide targets and the set of guides one gradient estimate uses.

The target of a guide is the boundary term's integrand in primary-sample space without the
velocity factor, F̃(u) = Σ_views max_RGB |F(u)| (docs/theory.md §5), evaluated by the estimator's own
code path (each guided term's :class:`~psdr_cli.estimators.term.GuideTarget`: for instance
:func:`~psdr_cli.estimators.direct.direct_target`, :func:`~psdr_cli.estimators.indirect.indirect_target`)
for the views the guide serves. For the indirect term F̃ contains one random source and detector subpath per
evaluation, a noisy but unbiased stand-in for the photon-map estimate of the paper's Eq. 11.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from ..estimators import registry
from ..estimators.boundary_sampling import edge_draw
from ..estimators.passes import make_sampler
from ..support.jitarray import jit_array
from .kdtree import share_profiles
from .kinds import guide_kind

#: lanes per batched target evaluation
CHUNK = 1 << 19


def motion_target(scene, sensors, edges, theta, motion, technique: str, u, *, mis: bool) -> mi.Float:
    """F̃(u) = Σ_views max_RGB |dv/dθ| of a term's samples (its ``motion``: forward mode from
    ``theta``, already applied to the scene with AD): the integrand itself, velocity included. The
    AD graph from θ is kept, so one application of θ serves every target of a build."""
    P = edges.positions(mi.traverse(scene.mi_scene))
    vs = motion(scene.mi_scene, sensors, edge_draw(edges, P), technique, u, mis=mis)
    dr.forward(theta, dr.ADFlag.ClearInput | dr.ADFlag.ClearInterior)
    total = mi.Float(0.0)
    for v in vs:
        total += dr.max(dr.abs(dr.grad(v)))
    dr.eval(total)
    return total


def target_function(scene, edges, views: list, term: str, technique: str, max_depth: int, seed: int, *,
                    mis: bool, theta=None):
    """numpy u (N,3) → F̃ (N,) for the guided ``term`` and ``technique`` (its
    :class:`~psdr_cli.estimators.term.GuideTarget`; ``mis``: whether the techniques are combined
    by MIS). With ``theta`` (the scalar parameter, applied
    with AD: forward mode) a term with a ``motion`` includes the velocity, F̃ = max_RGB |dv/dθ|
    (:func:`motion_target`); without it (optimisation: many parameters) F̃ = max_RGB |F| without
    the velocity factor. A term whose target is ``random`` gets a fresh sampler per batch."""
    target = registry.term(term).guide
    sensors = [scene.sensors[v] for v in views]
    mi_scene = scene.mi_scene
    calls = [0]

    def evaluate(u: np.ndarray) -> np.ndarray:
        out = np.empty(len(u))
        P = dr.detach(edges.positions(mi.traverse(mi_scene)))
        for a in range(0, len(u), CHUNK):
            chunk = u[a:a + CHUNK].astype(np.float32)
            pt = mi.Point3f(*(jit_array(mi.Float, chunk[:, i]) for i in range(3)))
            if theta is not None and target.motion is not None:
                val = motion_target(scene, sensors, edges, theta, target.motion, technique, pt, mis=mis)
            else:
                sampler = None
                if target.random:
                    calls[0] += 1
                    sampler = make_sampler(seed * 7919 + calls[0], len(chunk))
                val = target.evaluate(mi_scene, sensors, edge_draw(edges, P), technique, pt, sampler, max_depth,
                                      mis=mis)
            out[a:a + len(chunk)] = np.asarray(val, np.float64)
        return np.where(np.isfinite(out), out, 0.0)

    return evaluate


class Guides(dict):
    """The guides of one estimate by term name: ``guides["direct"]`` maps a technique (light, dir)
    to its guide, ``guides["indirect"]`` is one guide (of the ``dir`` technique); a term without an
    entry is unguided."""

    def all(self):
        """[(label, guide)] for reports, e.g. ``direct/light``."""
        out = []
        for term, guide in self.items():
            if isinstance(guide, dict):
                out += [(f"{term}/{t}", g) for t, g in guide.items()]
            elif guide is not None:
                out.append((f"{term}/dir", guide))
        return out


def applied_theta(parameter):
    """θ = 0 with AD enabled, applied to the scene (None without a parameter); the caller resets."""
    if parameter is None:
        return None
    theta = mi.Float(0.0)
    dr.enable_grad(theta)
    parameter.apply(theta)
    return theta


def build_guides(scene, edges, views: list, kinds: dict, sampling: str, max_depth: int, estimator, *,
                 seed: int = 0, parameter=None) -> Guides:
    """Guides for the terms of ``kinds`` ({term: guide kind}, as :func:`.auto.decide` decided
    them; ``none``: unguided), with the build parameters of ``estimator``; ``parameter`` (the
    scalar θ of a forward-mode gradient) puts the velocity into the targets of the terms that have
    a ``motion``."""
    guides = Guides()
    pixels = int(np.prod(scene.resolution))
    if edges.count == 0 or all(k == "none" for k in kinds.values()):
        return guides
    breaks = edges.breakpoints(dr.detach(edges.positions(mi.traverse(scene.mi_scene))))
    for term, kind in kinds.items():
        target = registry.term(term).guide
        if kind == "none" or max_depth < target.min_depth:
            continue
        theta = applied_theta(parameter) if target.motion is not None else None
        try:
            built = {}
            for i, t in enumerate(target.techniques(sampling)):
                f = target_function(scene, edges, views, term, t, max_depth, seed, mis=sampling == "mis", theta=theta)
                built[t] = guide_kind(kind).build(f, breaks, estimator, seed + target.seed_offset + i, pixels)
        finally:
            if theta is not None:
                parameter.reset()
        guides[term] = (share_profiles(built, breaks, estimator.kdtree.technique_share) if target.per_technique
                        else next(iter(built.values())))
    return guides
