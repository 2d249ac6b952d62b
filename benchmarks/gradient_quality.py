#!/usr/bin/env python
"""Gradient quality per second of a reconstruction's loss gradient: psdr's sample allocations and
the adjoint render against Mitsuba's recipe, on fixed shapes.

What an optimisation step uses is the gradient of the mini-batch L1 loss (4 views) with respect
to the LargeSteps latent u (V = (I + λL)⁻¹u), so that is what is measured: for a fixed shape,

    g = ∂/∂u (1/|B|) Σ_v mean |I_v − T_v|,

drawn K times with independent seeds per configuration, against a reference g* (psdr at 64
samples per pixel and term, the L1 sign from an independent 1024-spp render, mean of 4 draws;
psdr's estimators agree with finite differences, docs/gradients.md). Reported per configuration:
the median seconds t of one gradient, relMSE = E|g − g*|² / |g*|² split into variance and bias²,
cos(E[g], g*) and the efficiency 1/(relMSE·t) (higher is better: an estimator twice as
efficient reaches the same error in half the time by averaging).

Shapes: ``sphere`` (the remeshed initial sphere, 800 vertices: early iterations) and ``smooth``
(the ground truth remeshed to 1500 vertices and Laplacian-smoothed 8 times: late iterations,
creases and ears rounded).

    .venv/bin/python benchmarks/gradient_quality.py                # bunny, both shapes, K = 5
    .venv/bin/python benchmarks/gradient_quality.py --config configs/reconstruct_groove.yaml
    .venv/bin/python benchmarks/gradient_quality.py --only "psdr 1/4/1, adjoint 4 (configs)" --out /tmp/gq
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import psdr_cli  # noqa: E402,F401  (configures Dr.Jit / LLVM before drjit is imported)
import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402
import pymeshlab  # noqa: E402
from psdr_cli.estimators.boundary_sampling import edge_list  # noqa: E402
from psdr_cli.estimators.passes import pass_seed  # noqa: E402
from psdr_cli.experiment.load import load_experiment  # noqa: E402
from psdr_cli.geometry.remesh import remesh  # noqa: E402
from psdr_cli.losses.l1 import l1_loss  # noqa: E402
from psdr_cli.optimisation.engines import mitsuba_image, mitsuba_integrator  # noqa: E402
from psdr_cli.optimisation.iteration import adjoint_image  # noqa: E402
from psdr_cli.optimisation.problem import Problem, SceneSource, Shape  # noqa: E402
from psdr_cli.optimisation.start_state import initial_shape  # noqa: E402
from psdr_cli.rendering.estimate import Settings, ad_image  # noqa: E402
from psdr_cli.rendering.render import render_view  # noqa: E402
from psdr_cli.scene.build import build_scene  # noqa: E402
from psdr_cli.support import backend  # noqa: E402
from psdr_cli.support.fileio import atomic_path  # noqa: E402
from psdr_cli.target_sources.rendered_mesh import ground_truth  # noqa: E402

VIEWS = (0, 3, 6, 9)
TERMS = ("interior", "primary", "direct")
#: label -> ("psdr", interior spp, primary spp, boundary spp, adjoint spp[, primary_sampling]) or
#: ("mitsuba", spp, adjoint spp); psdr's primary_sampling is the experiment's unless given
CONFIGS = {
    "psdr 4/4/4 (before)": ("psdr", 4, 4, 4, 0),
    "psdr 4/4/4, adjoint 16": ("psdr", 4, 4, 4, 16),
    "psdr 4/16/4": ("psdr", 4, 16, 4, 0),
    "psdr 4/16/4, adjoint 16": ("psdr", 4, 16, 4, 16),
    "psdr 1/4/1, adjoint 4 (configs)": ("psdr", 1, 4, 1, 4),
    "psdr 1/4/1, adjoint 4, jump sampling": ("psdr", 1, 4, 1, 4, "jump"),
    "psdr 1/4/1, adjoint 16": ("psdr", 1, 4, 1, 16),
    "psdr 1/2/1, adjoint 4": ("psdr", 1, 2, 1, 4),
    "psdr 1/1/1, adjoint 4": ("psdr", 1, 1, 1, 4),
    "psdr 8/32/8, adjoint 32": ("psdr", 8, 32, 8, 32),
    "mitsuba 16 (recipe)": ("mitsuba", 16, 0),
    "mitsuba 16, adjoint 16": ("mitsuba", 16, 16),
    "mitsuba 4": ("mitsuba", 4, 0),
}


def fixed_shape(exp, reference, state: str):
    """(V, F) of the shape the gradients are taken at (see the module docstring)."""
    if state == "sphere":
        return remesh(*initial_shape(exp, reference), 800, "instant")
    V, F = remesh(*reference, 1500, "isotropic")
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(V, F.astype(np.int32)))
    ms.apply_coord_laplacian_smoothing(stepsmoothnum=8)
    return np.asarray(ms.current_mesh().vertex_matrix(), float), F


class Bench:
    """One fixed shape of one experiment, with its targets and a gradient sampler."""

    def __init__(self, exp, state: str):
        self.exp = exp
        reference = ground_truth(exp)
        scene = build_scene(exp, objects={exp.optimize.object: reference})
        self.targets = {v: mi.Float(np.asarray(render_view(scene, v, 256, seed=7919), np.float32).ravel())
                        for v in VIEWS}
        self.problem = Problem(SceneSource.of(exp), Shape(*fixed_shape(exp, reference, state)), None, {})
        self.settings = Settings.from_experiment(exp).with_estimator(guiding="none")

    def image(self, config, edges, view: int, draw: int):
        """The AD image of ``view`` by ``config`` and the adjoint render (None: its own sign)."""
        if config[0] == "mitsuba":
            est = replace(self.exp.estimator, engine="mitsuba")
            integrator = mitsuba_integrator(est, self.settings.max_depth)
            seed = pass_seed(0, view, draw, 9)
            img = mitsuba_image(self.problem.scene, self.problem.params, integrator, view, config[1], seed)
            adjoint = config[2]
        else:
            s = self.settings.with_estimator(spp=config[1], primary_spp=config[2], boundary_spp=config[3],
                                             primary_sampling=config[5] if len(config) > 5
                                             else self.exp.estimator.primary_sampling)
            img = ad_image(self.problem.scene, edges, view, TERMS, s, pass_index=draw)
            adjoint = config[4]
        return img, (adjoint_image(self.problem.scene, view, adjoint, 12345, draw) if adjoint else None)

    def gradient(self, config, draw: int) -> np.ndarray:
        """One draw of ∂L/∂u for the 4-view batch."""
        p, name = self.problem, self.exp.optimize.object
        p.apply()
        p.scene.objects[name].vertices, p.scene.objects[name].faces = p.vertices(), p.F
        edges = edge_list(p.scene, self.exp.estimator, False)
        loss = mi.Float(0.0)
        for v in VIEWS:
            img, adjoint = self.image(config, edges, v, draw)
            loss += l1_loss(img, self.targets[v], adjoint) / len(VIEWS)
        dr.backward(loss)
        g = np.asarray(dr.grad(p.opt["u"]), np.float64).copy()
        dr.set_grad(p.opt["u"], 0.0)
        return g


def measure(bench: Bench, trials: int, labels) -> dict:
    reference = [bench.gradient(("psdr", 64, 64, 64, 1024), 1000 + k) for k in range(4)]
    g_ref = np.mean(reference, 0)
    norm = float(np.sum(g_ref ** 2))
    rows = {}
    for label in labels:
        config = CONFIGS[label]
        bench.gradient(config, 0)  # compiles the kernels
        times, draws = [], []
        for k in range(trials):
            t0 = time.perf_counter()
            draws.append(bench.gradient(config, 1 + k))
            times.append(time.perf_counter() - t0)
        draws = np.array(draws)
        mean = draws.mean(0)
        mse = float(np.mean(np.sum((draws - g_ref) ** 2, 1)) / norm)
        var = float(np.sum((draws - mean) ** 2) / (trials - 1) / norm)
        t = float(np.median(times))
        rows[label] = {"seconds": t, "relMSE": mse, "variance": var, "bias2": max(mse - var, 0.0),
                       "cos": float(mean @ g_ref / np.linalg.norm(mean) / np.linalg.norm(g_ref)),
                       "efficiency": 1.0 / (mse * t)}
        print(f"{label:36s} {t:.3f} s  relMSE {mse:.4f}  1/(relMSE·t) {1 / (mse * t):.1f}", flush=True)
    return rows


def table(rows: dict) -> list:
    base = rows["mitsuba 16 (recipe)"]["efficiency"]
    out = ["| configuration | seconds per gradient | relMSE | variance | bias² | cos(E[g], g*) | 1/(relMSE·t) | vs Mitsuba 16 |",
           "|---|---|---|---|---|---|---|---|"]
    for label, r in rows.items():
        out.append(f"| {label} | {r['seconds']:.3f} | {r['relMSE']:.4f} | {r['variance']:.4f} | {r['bias2']:.4f} "
                   f"| {r['cos']:.3f} | {r['efficiency']:.1f} | {r['efficiency'] / base:.2f}× |")
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--config", type=Path, default=REPO / "configs" / "reconstruct_bunny.yaml")
    ap.add_argument("--states", nargs="+", default=["sphere", "smooth"], choices=["sphere", "smooth"])
    ap.add_argument("--trials", type=int, default=5, help="gradient draws per configuration (K)")
    ap.add_argument("--out", type=Path, default=REPO / "docs" / "benchmarks")
    ap.add_argument("--only", nargs="+", choices=list(CONFIGS), default=list(CONFIGS), metavar="LABEL",
                    help="measure only these configurations (labels of CONFIGS; default: all)")
    args = ap.parse_args(argv)
    labels = args.only if "mitsuba 16 (recipe)" in args.only else args.only + ["mitsuba 16 (recipe)"]
    exp = load_experiment(args.config)
    backend.activate(exp)
    dr.set_thread_count(int(os.environ.get("PSDR_OPTIMIZE_THREADS", "1")))
    results = {}
    for state in args.states:
        print(f"== {args.config.name}, {state}", flush=True)
        results[state] = measure(Bench(exp, state), args.trials, labels)
    md = ["# Gradient quality per second: psdr's allocations vs Mitsuba's recipe", "",
          f"`benchmarks/gradient_quality.py {' '.join(sys.argv[1:])}` — {time.strftime('%Y-%m-%d %H:%M')}, "
          f"{platform.machine()}, {os.cpu_count()} cores, one Dr.Jit thread; {args.config.name}, views "
          f"{list(VIEWS)} per gradient, K = {args.trials} draws. Configurations: interior/primary/boundary spp "
          "and the adjoint render's spp (`optimize.adjoint_spp`; none: the sign of the AD image's own primal). "
          "Reference g*: psdr 64/64/64 with a 1024-spp adjoint, mean of 4 draws. relMSE = E|g − g*|²/|g*|² "
          "(variance + bias²), efficiency 1/(relMSE·t).", ""]
    for state, rows in results.items():
        md += [f"## {state}", ""] + table(rows) + [""]
    args.out.mkdir(parents=True, exist_ok=True)
    stem = f"gradient_quality_{args.config.stem}"
    with atomic_path(args.out / f"{stem}.md") as tmp:
        Path(tmp).write_text("\n".join(md))
    with atomic_path(args.out / f"{stem}.json") as tmp:
        Path(tmp).write_text(json.dumps(results, indent=1))
    print("\n".join(md))


if __name__ == "__main__":
    main()
