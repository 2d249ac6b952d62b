"""``psdr guide-stats``: guide sizes and costs, edge chains, the target along u1 (paper Fig. 5).
Reads the experiment; writes guide_stats.json and its plots."""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

from ..config.experiment_file import Experiment
from ..config.options import parse_views
from ..errors import PsdrError
from ..estimators import registry
from ..estimators.boundary_sampling import edge_distribution, edge_list, sample_edge_point
from ..estimators.registry import GUIDED
from ..scene.build import build_scene
from ..support import backend, fileio, plots
from ..support.jitarray import jit_array
from .kinds import NAMES as GUIDE_KINDS, guide_kind
from .targets import target_function


def chain_stats(edges) -> dict:
    """Edges, chains (continuous pieces of x^B(u1)) and mean chain length."""
    return {"edges": int(edges.count), "chains": int(edges.chains.count),
            "mean_chain_length": float(edges.chains.mean_length())}


def target_curve(scene, edges, views, term: str, technique: str, max_depth: int, *, n_u1: int = 2048,
                 n_u2: int = 16, seed: int = 0):
    """(u1, x^B(u1) (N,3), mean over u2 of F̃ of ``term``'s ``technique`` (N,), breakpoints) for plots."""
    u1 = (np.arange(n_u1) + 0.5) / n_u1
    rng = np.random.default_rng(seed)
    u = np.concatenate([np.repeat(u1, n_u2)[:, None], rng.random((n_u1 * n_u2, 2))], axis=1)
    f = target_function(scene, edges, views, term, technique, max_depth, seed, mis=False)
    mean = f(u).reshape(n_u1, n_u2).mean(1)
    P = dr.detach(edges.positions(mi.traverse(scene.mi_scene)))
    with dr.suspend_grad():
        e = sample_edge_point(edges, P, edge_distribution(edges, P), jit_array(mi.Float, u1))
        xB = np.stack([np.asarray(e.xB[i], np.float64) for i in range(3)], 1)
    return u1, xB, mean, edges.breakpoints(P)


def pass_seconds(scene, edges, view: int, term: str, estimator, max_depth: int, repeats: int = 3) -> float:
    """Median seconds of one unguided pass of ``term`` with ``estimator.boundary_spp`` samples per
    pixel (the term's own ``estimate``, evaluated), after one warm-up pass."""
    times = []
    for r in range(repeats + 1):
        t0 = time.perf_counter()
        img = registry.term(term).estimate(scene, edges, view, estimator.boundary_spp, r, estimator, max_depth)
        dr.eval(img)
        times.append(time.perf_counter() - t0)
    return float(np.median(times[1:]))


def guided_techniques(terms, sampling: str, max_depth: int) -> list:
    """[(label, term, technique)] of the guides ``psdr guide-stats`` builds, in seed order: one per
    technique of a guided term among ``terms`` (labelled by the technique, or by the term when it
    has one guide), none for a term the scene's ``max_depth`` leaves out."""
    out = []
    for term in GUIDED:
        target = registry.term(term).guide
        if term in terms and max_depth >= target.min_depth:
            out += [(t if target.per_technique else term, term, t) for t in target.techniques(sampling)]
    return out


def guide_report(scene, edges, views, kinds, techniques, max_depth: int, estimator, *, seed: int = 0):
    """Build every (kind, technique) guide of ``techniques`` (:func:`guided_techniques`); returns
    ({label: GuideStats-dict}, {label: guide}).

    Targets use the MIS weights when ``estimator.sampling`` is ``mis`` (as the estimator does);
    kernels are compiled by a small warm-up call first, so build seconds are steady-state.
    ``build_over_pass`` divides the build by one unguided pass of the guided term with
    ``boundary_spp`` samples per pixel (for MIS, each of the two guides against the whole pass)."""
    breaks = edges.breakpoints(dr.detach(edges.positions(mi.traverse(scene.mi_scene))))
    pixels = int(np.prod(scene.resolution))
    passes = {term: pass_seconds(scene, edges, views[0], term, estimator, max_depth)
              for term in {term for _, term, _ in techniques}}
    stats, guides = {}, {}
    for kind in kinds:
        for i, (t, term, technique) in enumerate(techniques):
            f = target_function(scene, edges, views, term, technique, max_depth, seed, mis=estimator.sampling == "mis")
            f(np.random.default_rng(0).random((1024, 3)))  # warm-up: compile the target's kernels
            g = guide_kind(kind).build(f, breaks, estimator, seed + i, pixels)
            label = f"{kind}/{t}"
            s = g.stats
            stats[label] = {"guide": kind, "technique": t, "leaves": s.leaves, "max_depth": s.max_depth,
                            "memory_bytes": s.memory_bytes, "build_seconds": s.build_seconds,
                            "evaluations": s.evaluations, "normalization": s.normalization,
                            "u1_intervals": s.intervals, "pass_seconds": passes[term],
                            "build_over_pass": s.build_seconds / max(passes[term], 1e-9)}
            guides[label] = g
    return stats, guides


@dataclass
class GuideStatsResult:
    folder: Path
    guides: dict = field(default_factory=dict)     # {"sorted|unsorted": {label: stats}}
    chains: dict = field(default_factory=dict)     # {"sorted|unsorted": chain stats}
    plots: list = field(default_factory=list)


def guide_stats(exp: Experiment, kinds=None, views=None, out: Path | None = None, progress=None) -> GuideStatsResult:
    """Build the boundary guides of an experiment with and without edge sorting and report them.

    ``kinds``: guides to build (default: ``estimator.guiding``, or every guide kind when it is
    ``none`` or ``auto``). Writes ``guide_stats.json``, ``target_u1.png`` per technique (x^B and the target
    along u1, unsorted vs sorted: the paper's Fig. 5) and ``leaves_<kind>_<technique>.png``
    (leaf boundaries in the plane u2.y = ½) to ``<output>/<name>/guide_stats/``."""
    variant = backend.activate(exp)
    kinds = kinds or ([exp.estimator.guiding] if exp.estimator.guiding in GUIDE_KINDS else list(GUIDE_KINDS))
    if isinstance(kinds, str):
        kinds = [k.strip() for k in kinds.split(",") if k.strip()]
    bad = [k for k in kinds if k not in GUIDE_KINDS]
    if bad:
        raise PsdrError(f"--guides: unknown guide '{bad[0]}' (expected {' and/or '.join(GUIDE_KINDS)})")
    scene = build_scene(exp)
    views = parse_views(views, len(exp.scene.cameras))
    terms = exp.estimator.terms
    max_depth = exp.scene.max_depth
    techniques = guided_techniques(terms, exp.estimator.sampling, max_depth)
    if not techniques:
        raise PsdrError(f"{exp.file}: estimator.terms: guides serve the direct and indirect terms; "
                        f"none of them is requested")
    folder = exp.command_dir("guide_stats", out)
    result = GuideStatsResult(folder)
    curves = {t: {} for t, _, _ in techniques}
    if progress:
        progress.start(2 * (len(kinds) * len(techniques) + len(techniques)))
    for sort in (False, True):
        key = "sorted" if sort else "unsorted"
        edges = edge_list(scene, exp.estimator, sort)
        if edges.count == 0:
            raise PsdrError(f"{exp.file}: scene.objects: no object has boundary edges (edges: true)")
        result.chains[key] = chain_stats(edges)
        stats, guides = guide_report(scene, edges, views, kinds, techniques, max_depth, exp.estimator, seed=exp.seed)
        result.guides[key] = stats
        if progress:
            progress.advance(len(kinds) * len(techniques))
        for t, term, technique in techniques:
            curves[t][f"{key} edges"] = target_curve(scene, edges, views, term, technique, max_depth, seed=exp.seed)
            if progress:
                progress.advance(1)
        for label, g in guides.items():
            kind, t = label.split("/")
            png = folder / f"leaves_{kind}_{t}_{key}.png"
            centre = 0.5 * (g.lo + g.hi)
            c = float(centre[np.argmax(g.mass), 0]) if g.total > 0 else 0.5
            window = (max(0.0, c - 0.025), min(1.0, c + 0.025))  # around the heaviest leaf
            plots.leaf_slice(png, g.lo, g.hi, g.pdf_np(centre), u1_range=window,
                             title=f"{kind} guide, {t} ({key} edges): {g.stats.leaves} leaves; slice u2.y = ½, "
                                   f"u1 ∈ [{window[0]:.3f}, {window[1]:.3f}]")
            result.plots.append(png)
    for t in curves:
        png = folder / f"target_u1_{t}.png"
        plots.target_along_u1(png, curves[t], title=f"{exp.name}: {t} target along u1")
        result.plots.append(png)
    fileio.write_json(folder / "guide_stats.json", {
        "experiment": str(exp.file), "variant": variant, "views": views, "sampling": exp.estimator.sampling,
        "epsilon": exp.estimator.guide_epsilon, "chains": result.chains, "guides": result.guides,
        "plots": [str(p) for p in result.plots]})
    return result
