#!/usr/bin/env python
"""What the optimiser sees: the error of the loop's reverse-mode gradient, per term and guide.

At a fixed shape V (a checkpoint of a run) and a fixed mini-batch B of views, the loop's step
uses the gradient of its L1 loss with respect to the LargeSteps latent u (V = (I + λL)⁻¹u). With
the L1 sign s_v = sign(Ī_v − T_v) taken from a high-sample render Ī_v, the loss is linear in the
images and its gradient is the sum of one gradient per term:

    g = Σ_term g_term,   g_term = (1/|B|) Σ_{v∈B} ∂/∂u ⟨s_v, I_{v,term}(V(u))⟩ / (3·W·H)

(for the raw per-vertex gradient ∂L/∂V the same with V in place of u). Each term's estimator is
unbiased (guided or not: docs/guiding.md, tests/test_guiding.py), so its error is its variance,
measured from K independent draws; it is reported relative to |g*|², where g* is the total
gradient estimated by the unguided estimators at ``--ref-factor`` times the configuration's
samples (mean of R draws):

    relVar_term = E|g_term − E g_term|² / |g*|²        (the terms' shares add up to the total's)

Seconds are the median of one draw of one term over the batch, and the guides' build seconds
(the loop rebuilds them every ``optimize.guide_every`` iterations, over all views) are added per
iteration: t = t_draw + t_build / guide_every. Efficiency 1/(relVar·t): higher is better.

Variants: ``none`` (unguided), ``grid``, ``kdtree`` with the experiment's sampling and its
variants' edge sorting, and ``kdtree, batch views``: the Kd-tree built only from the batch's
views (the loop builds its guides from all views; this variant shows what that costs).

    .venv/bin/python benchmarks/guided_gradients.py configs/paper/cpu/fig10_shadow.yaml \\
        --states runs/paper/cpu/fig10_shadow/unguided/checkpoints/iter_0100.ply ...
"""
from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import psdr_cli  # noqa: E402,F401  (configures Dr.Jit / LLVM before drjit is imported)
import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402
from psdr_cli.estimators.boundary_sampling import edge_list  # noqa: E402
from psdr_cli.estimators.sample_log import SampleLog  # noqa: E402
from psdr_cli.experiment.load import load_experiment  # noqa: E402
from psdr_cli.guiding.loop_fed import fitted_guides, per_pass_budget  # noqa: E402
from psdr_cli.guiding.targets import Guides  # noqa: E402
from psdr_cli.optimisation.iteration import batch_views  # noqa: E402
from psdr_cli.optimisation.problem import Problem, SceneSource, Shape  # noqa: E402
from psdr_cli.rendering.estimate import Settings, ad_image, make_guides, term_image  # noqa: E402
from psdr_cli.rendering.render import render_view  # noqa: E402
from psdr_cli.scene.build import build_scene  # noqa: E402
from psdr_cli.scene.meshes import read_mesh_file  # noqa: E402
from psdr_cli.support import backend  # noqa: E402
from psdr_cli.support.fileio import atomic_path, write_json  # noqa: E402

#: label -> (guiding, where the guides come from: built from all views / from the batch's views /
#: fitted to the loop's own samples, edge sorting (None: the experiment's variant of that kind))
VARIANTS = {
    "none": ("none", "all", None),
    "grid": ("grid", "all", None),
    "kdtree": ("kdtree", "all", None),
    "kdtree, batch views": ("kdtree", "batch", None),
    "kdtree, loop-fed": ("kdtree", "loop", None),
    "kdtree, loop-fed, unsorted": ("kdtree", "loop", False),
}


class Bench:
    """One shape of one experiment: the loop's differentiable state, sign images and batch."""

    def __init__(self, exp, V, F, views, target_spp: int, sign_spp: int):
        self.exp, self.views = exp, list(views)
        truth = build_scene(exp)
        targets = {v: np.asarray(render_view(truth, v, target_spp, seed=7919), np.float64) for v in self.views}
        self.problem = Problem(SceneSource.of(exp), Shape(V, F), None, {})
        self.problem.apply()
        name = exp.optimize.object
        self.problem.scene.objects[name].vertices = self.problem.vertices()
        self.problem.scene.objects[name].faces = self.problem.F
        self.signs = {v: mi.Float(np.sign(np.asarray(render_view(self.problem.scene, v, sign_spp, seed=104729),
                                                     np.float64) - targets[v]).ravel().astype(np.float32))
                      for v in self.views}
        self.edges = {}

    @property
    def scene(self):
        return self.problem.scene

    def edges_for(self, edge_sort: bool):
        if edge_sort not in self.edges:
            self.edges[edge_sort] = edge_list(self.scene, self.exp.estimator, edge_sort)
        return self.edges[edge_sort]

    def gradient(self, terms, settings: Settings, edge_sort: bool, guides, draw: int):
        """(∂L/∂u, ∂L/∂V) of the sign-fixed batch loss restricted to ``terms``; ∂L/∂V = (I + λL) ∂L/∂u,
        since ∂V/∂u = (I + λL)⁻¹ is symmetric."""
        p = self.problem
        p.apply()
        loss = mi.Float(0.0)
        for v in self.views:
            img = ad_image(self.scene, self.edges_for(edge_sort), v, terms, settings, pass_index=draw, guides=guides)
            loss += dr.sum(self.signs[v] * img) / (dr.width(img) * len(self.views))
        dr.backward(loss, flags=dr.ADFlag.Default | dr.ADFlag.AllowNoGrad)
        g_u = dr.grad(p.opt["u"])
        dr.set_grad(p.opt["u"], 0.0)
        with dr.suspend_grad():
            g_v = p.steps.to_differential(dr.detach(g_u))
        return np.asarray(g_u, np.float64).copy(), np.asarray(g_v, np.float64).copy()

    def guides(self, settings: Settings, edge_sort: bool, terms, source: str):
        """(guides, seconds of building them): built from all views or the batch's, or (``loop``)
        fitted as the loop fits them: two windows of ``guide_every`` iterations of the loop's
        mini-batches at this shape, the first unguided, the second with the guides fitted to the
        first; the guides fitted to the second are measured and only their fit is timed (the
        passes are the loop's own)."""
        edges = self.edges_for(edge_sort)
        with dr.suspend_grad():
            if source != "loop":
                t0 = time.perf_counter()
                views = self.views if source == "batch" else list(range(len(self.scene.sensors)))
                guides = make_guides(self.scene, edges, views, terms, settings)
                return guides, time.perf_counter() - t0
            cfg = self.exp.optimize
            budget = per_pass_budget(cfg.guide_every * cfg.batch_size)
            breaks = edges.breakpoints(dr.detach(edges.positions(mi.traverse(self.scene.mi_scene))))
            log, t_fit = SampleLog({}, budget), 0.0
            for window in range(2):
                for it in range(cfg.guide_every):
                    for v in batch_views(self.exp.seed, 1000 * window + it, len(self.scene.sensors), cfg.batch_size):
                        term_image(self.scene, edges, v, "direct", settings.boundary_spp, 90000 + 100 * it + v,
                                   settings, guides=Guides(direct=log))
                t0 = time.perf_counter()
                log = SampleLog(fitted_guides(log, breaks, settings.estimator), budget)
                t_fit = time.perf_counter() - t0
            return Guides(direct=dict(log)), t_fit


def variant_settings(exp, guiding: str) -> tuple[Settings, bool]:
    """Settings of a variant and its edge sorting (the experiment's variant of that guide kind)."""
    edge_sort = exp.estimator.edge_sort
    for v in (exp.optimize.variants or ()):
        if v.guiding == guiding:
            edge_sort = edge_sort if v.edge_sort is None else v.edge_sort
            break
    return Settings.from_experiment(exp).with_estimator(guiding=guiding, edge_sort=edge_sort), edge_sort


def reference(bench: Bench, exp, factor: int, draws: int):
    """g* (u and V) by the unguided estimators at ``factor`` × the configuration's samples."""
    e = exp.estimator
    settings = Settings.from_experiment(exp).with_estimator(
        guiding="none", spp=e.spp * factor, primary_spp=e.primary_spp * factor, boundary_spp=e.boundary_spp * factor)
    pairs = [bench.gradient(e.terms, settings, False, None, 5000 + k) for k in range(draws)]
    return np.mean([p[0] for p in pairs], 0), np.mean([p[1] for p in pairs], 0)


def measure(bench: Bench, exp, trials: int, ref_factor: int, ref_draws: int, labels) -> dict:
    g_ref_u, g_ref_v = reference(bench, exp, ref_factor, ref_draws)
    norm_u, norm_v = float(np.sum(g_ref_u ** 2)), float(np.sum(g_ref_v ** 2))
    guide_every = exp.optimize.guide_every
    rows = {}
    for label in labels:
        guiding, source, sort = VARIANTS[label]
        settings, edge_sort = variant_settings(exp, guiding)
        edge_sort = edge_sort if sort is None else sort
        guides, t_build = bench.guides(settings, edge_sort, exp.estimator.terms, source)
        t_build = t_build if guiding != "none" else 0.0
        row = {"build_seconds": t_build, "terms": {}}
        total_u, total_v, total_t = 0.0, 0.0, 0.0
        for term in exp.estimator.terms:
            bench.gradient([term], settings, edge_sort, guides, 0)  # compiles the kernels
            times, gu, gv = [], [], []
            for k in range(trials):
                t0 = time.perf_counter()
                a, b = bench.gradient([term], settings, edge_sort, guides, 1 + k)
                times.append(time.perf_counter() - t0)
                gu.append(a)
                gv.append(b)
            gu, gv = np.array(gu), np.array(gv)
            var_u = float(np.sum(gu.var(0, ddof=1)) / norm_u)
            var_v = float(np.sum(gv.var(0, ddof=1)) / norm_v)
            t = float(np.median(times))
            row["terms"][term] = {"seconds": t, "relvar_u": var_u, "relvar_V": var_v}
            total_u, total_v, total_t = total_u + var_u, total_v + var_v, total_t + t
        t_iter = total_t + t_build / guide_every
        row.update(seconds=t_iter, relvar_u=total_u, relvar_V=total_v, efficiency_u=1.0 / (total_u * t_iter),
                   efficiency_V=1.0 / (total_v * t_iter))
        rows[label] = row
        shares = ", ".join(f"{t} {r['relvar_u']:.4f}" for t, r in row["terms"].items())
        print(f"  {label:22s} t {t_iter:.3f} s (build {t_build:.2f} s)  relVar_u {total_u:.4f} [{shares}]  "
              f"relVar_V {total_v:.4f}  eff_u {row['efficiency_u']:.1f}", flush=True)
    return rows


def table(rows: dict, terms) -> list:
    base = rows["none"]
    out = ["| variant | s / iteration (guide build) | " + " | ".join(f"relVar_u {t}" for t in terms)
           + " | relVar_u total | relVar_V total | efficiency (u) vs unguided | per iteration (u) vs unguided |",
           "|---|---|" + "---|" * len(terms) + "---|---|---|---|"]
    for label, r in rows.items():
        out.append(f"| {label} | {r['seconds']:.3f} ({r['build_seconds']:.2f}) | "
                   + " | ".join(f"{r['terms'][t]['relvar_u']:.4f}" for t in terms)
                   + f" | {r['relvar_u']:.4f} | {r['relvar_V']:.4f} | {r['efficiency_u'] / base['efficiency_u']:.2f}× "
                   f"| {base['relvar_u'] / r['relvar_u']:.2f}× |")
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("config", type=Path)
    ap.add_argument("--states", nargs="+", type=Path, required=True, help="meshes (PLY/OBJ) the gradient is taken at")
    ap.add_argument("--views", type=int, nargs="+", default=None, help="the batch (default: the first batch_size views)")
    ap.add_argument("--trials", type=int, default=8, help="draws per term and variant (K)")
    ap.add_argument("--ref-factor", type=int, default=16, help="the reference's samples per configuration sample")
    ap.add_argument("--ref-draws", type=int, default=4, help="draws averaged by the reference (R)")
    ap.add_argument("--variants", nargs="+", choices=list(VARIANTS), default=list(VARIANTS))
    ap.add_argument("--out", type=Path, default=REPO / "docs" / "benchmarks")
    args = ap.parse_args(argv)
    exp = load_experiment(args.config)
    backend.activate(exp)
    dr.set_thread_count(int(os.environ.get("PSDR_OPTIMIZE_THREADS", "2")))
    views = args.views or list(range(exp.optimize.batch_size))
    labels = ["none"] + [v for v in args.variants if v != "none"]
    results = {}
    for path in args.states:
        V, F = read_mesh_file(path)
        print(f"== {args.config.name}, {path.name} ({len(V)} vertices), views {views}", flush=True)
        bench = Bench(exp, V, F, views, exp.optimize.target_spp, 1024)
        results[path.name] = measure(bench, exp, args.trials, args.ref_factor, args.ref_draws, labels)
    e = exp.estimator
    md = [f"# What the optimiser sees: {args.config.name}", "",
          f"`benchmarks/guided_gradients.py {' '.join(sys.argv[1:])}` — {time.strftime('%Y-%m-%d %H:%M')}, "
          f"{platform.machine()}, {os.cpu_count()} cores; batch views {views}, K = {args.trials} draws, samples "
          f"{e.spp}/{e.primary_spp}/{e.boundary_spp} (interior/primary/boundary), sampling {e.sampling}, guides "
          f"rebuilt every {exp.optimize.guide_every} iterations. relVar_u: variance of ∂L/∂u (the LargeSteps "
          f"latent the step uses) over |g*|²; relVar_V the same for ∂L/∂V; g* unguided at {args.ref_factor}× "
          f"the samples, mean of {args.ref_draws} draws. Efficiency 1/(relVar·t), t including the guide build "
          "amortised over its iterations.", ""]
    for state, rows in results.items():
        md += [f"## {state}", ""] + table(rows, e.terms) + [""]
    args.out.mkdir(parents=True, exist_ok=True)
    stem = f"guided_gradients_{args.config.stem}"
    with atomic_path(args.out / f"{stem}.md") as tmp:
        Path(tmp).write_text("\n".join(md))
    write_json(args.out / f"{stem}.json", results)
    print("\n".join(md))


if __name__ == "__main__":
    main()
