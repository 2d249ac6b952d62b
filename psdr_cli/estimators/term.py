"""The interface every term of dI/dθ implements, like Mitsuba 3's integrators share one signature.

A term is a :class:`Term`: its name (the word in ``estimator.terms``), the estimator key holding
its samples per pixel, its random-number stream, whether a guide can serve it, and ``estimate``,
which computes one pass:

    estimate(scene, edges, view, spp, seed, estimator, max_depth, guide) -> mi.Float

``scene`` is a :class:`psdr_cli.scene.Scene` or anything with its ``mi_scene``, ``sensors`` and
``resolution`` (W, H); its AD state (θ or vertex gradients) is set before the call. ``edges`` are
the boundary edges, ``spp`` the samples per pixel of this pass, ``seed`` its sampler seed,
``estimator`` the experiment's :class:`psdr_cli.config.EstimatorConfig`, ``max_depth`` the scene's
path depth and ``guide`` the term's guide (None: unguided). The result is a flat W·H·3 image
attached to the AD graph: the interior term's primal value is the rendered image, a boundary
term's primal value is 0 (it only carries derivatives).

Each estimator module declares its ``TERM``; :mod:`.registry` lists them.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import mitsuba as mi

from .passes import make_sampler


@dataclass(frozen=True)
class Term:
    """One term of dI/dθ (module docstring)."""
    name: str
    samples_key: str      # EstimatorConfig field with its samples per pixel (spp, primary_spp, boundary_spp)
    stream: int           # random-number stream of its passes (estimators.passes.pass_seed)
    guided: bool          # whether a boundary guide can serve it (guiding/targets.py)
    estimate: Callable[..., mi.Float]


def boundary_pass(scene, edges, spp: int, seed: int):
    """(N, sampler, P) of one boundary pass: N = spp · W · H samples, their sampler and the AD
    vertex buffer of the edge objects (None without edges)."""
    width, height = scene.resolution
    n = spp * width * height
    sampler = make_sampler(seed, n)
    P = edges.positions(mi.traverse(scene.mi_scene)) if edges.count else None
    return n, sampler, P
