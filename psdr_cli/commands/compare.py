"""Equal-time and equal-sample comparisons of boundary estimators (``psdr compare``). Reads the
experiment; writes the comparison's EXRs, grid, compare.md and compare.json.

A comparison renders the forward-mode gradient image of one view and the given terms (usually
``direct``/``indirect``) with several *variants* (guiding × sampling × edge sorting) and measures

    relMSE = Σ (g − ref)² / Σ ref² − relMSE(ref)

against a high-sample unguided MIS reference whose own expected error (from the spread of its
passes) is subtracted. A variant either gets a wall-clock budget (its guides are built first and
their time counts; passes of ``boundary_spp`` are rendered until the budget is spent, and the
error is scaled by time used / budget, as variance ∝ 1/time) or a fixed number of passes (equal
samples). Trials use distinct seeds and their errors are averaged.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ..config.experiment_file import Experiment
from ..config.options import with_estimator
from ..config.variants_section import Variant
from ..errors import PsdrError
from ..estimators.boundary_sampling import edge_list
from ..rendering import estimate
from ..rendering.estimate import Settings, make_guides, prepare
from ..support import fileio, plots

#: The variant of the reference image: unguided MIS over unsorted edges.
REFERENCE = Variant("reference", guiding="none", sampling="mis", edge_sort=False)


def rel_mse(g, ref) -> float:
    """Σ (g − ref)² / Σ ref²."""
    return float(((g - ref) ** 2).sum() / max((ref ** 2).sum(), 1e-30))


@dataclass
class Row:
    variant: Variant
    rel_mse: float
    rel_mse_trials: list
    seconds: list
    passes: list
    build_seconds: float
    pass_seconds: float
    guides: dict = field(default_factory=dict)
    image: np.ndarray | None = None

    @property
    def build_over_pass(self) -> float:
        return self.build_seconds / self.pass_seconds if self.variant.guiding not in (None, "none") else 0.0


class Comparison:
    """One scene and view: the experiment, its Mitsuba scene and edge lists (unsorted, sorted)."""

    def __init__(self, exp, terms, view: int = 0):
        self.exp, self.terms, self.view = exp, tuple(terms), view
        self.scene, self.parameter, _, _ = prepare(exp)
        self.edges = {s: edge_list(self.scene, exp.estimator, s) for s in (False, True)}

    def settings(self, variant: Variant, seed: int) -> Settings:
        exp = with_estimator(self.exp, guiding=variant.guiding, sampling=variant.sampling,
                             edge_sort=variant.edge_sort)
        return Settings.from_experiment(exp, seed=seed)

    def guides(self, variant: Variant, seed: int):
        """(guides, build seconds) for the variant (empty and 0 without guiding)."""
        t0 = time.perf_counter()
        st = self.settings(variant, seed)
        g = make_guides(self.scene, self.edges[st.edge_sort], [self.view], self.terms, st, self.parameter)
        return g, time.perf_counter() - t0

    def pass_settings(self, variant: Variant, seed: int, term: str, n: int):
        """Settings of ``n`` passes of ``term``: its per-pass sample count times ``n``
        (a fresh copy per term, so the terms' counts do not compound)."""
        st = self.settings(variant, seed)
        return st.with_samples(term, st.samples(term) * n).with_estimator(passes=n)

    def passes(self, variant: Variant, seed: int, n: int, guides):
        """(mean image over n passes of boundary_spp, per-pass images, seconds)."""
        total, images, seconds = None, [], 0.0
        for term in self.terms:
            st = self.pass_settings(variant, seed, term, n)
            est = estimate.forward_gradient(self.scene, self.edges[st.edge_sort], self.parameter, self.view, term, st,
                                   n, guides=guides)
            images = est.passes if not images else [a + b for a, b in zip(images, est.passes)]
            total = est.gradient if total is None else total + est.gradient
            seconds += est.seconds
        return total, images, seconds

    def reference(self, passes: int):
        """(image, its own expected relMSE, seconds): unguided MIS with ``passes`` passes."""
        ref, images, seconds = self.passes(REFERENCE, 99, passes, None)
        noise = float(np.var(images, axis=0, ddof=1).sum() / passes / max((ref ** 2).sum(), 1e-30))
        return ref, noise, seconds

    def trial(self, variant: Variant, seed: int, budget: float):
        """(image, seconds, build seconds, passes, guides): guides, then passes until the budget
        is spent (or ``variant.passes`` passes)."""
        t0 = time.perf_counter()
        guides, build = self.guides(variant, seed)
        images, n = [], 0
        while True:
            images.append(self.passes(variant, seed * 1000 + n, 1, guides)[0])
            n += 1
            if (variant.passes is not None and n >= variant.passes) or \
                    (variant.passes is None and time.perf_counter() - t0 >= budget):
                break
        return np.mean(images, axis=0), time.perf_counter() - t0, build, n, guides

    def measure(self, variant: Variant, ref, ref_noise: float, budget: float, trials: int) -> Row:
        """Warm up (kernel compilation), time one pass, then run the trials."""
        self.trial(replace(variant, passes=1), 7, 0.0)
        guides, _ = self.guides(variant, 5)
        _, _, pass_seconds = self.passes(variant, 5, 1, guides)
        errs, used, builds, counts, image = [], [], [], [], None
        for t in range(trials):
            img, secs, build, n, guides = self.trial(variant, 11 + t, budget)
            scale = secs / budget if variant.passes is None else 1.0
            errs.append((rel_mse(img, ref) - ref_noise) * scale)
            used.append(secs), builds.append(build), counts.append(n)
            image = img if image is None else image
        stats = {k: {"leaves": g.stats.leaves, "max_depth": g.stats.max_depth, "memory_bytes": g.stats.memory_bytes,
                     "evaluations": g.stats.evaluations} for k, g in guides.all()}
        return Row(variant, float(np.mean(errs)), errs, used, counts, float(np.mean(builds)), pass_seconds,
                   stats, image)


@dataclass
class CompareResult:
    folder: Path
    rows: list = field(default_factory=list)     # psdr_cli.commands.compare.Row
    reference_rel_mse: float = 0.0


def run_comparison(exp: Experiment, out: Path | None = None, progress=None) -> CompareResult:
    """Run the experiment's ``compare:`` section ; writes
    ``compare.json``, ``compare.md``, ``grid.png`` and one EXR per variant to
    ``<output>/<name>/compare/``."""
    cfg = check_comparison(exp)
    folder = exp.command_dir("compare", out)
    c = Comparison(exp, cfg.terms, cfg.view)
    if progress:
        progress.start(len(cfg.variants) + 1)
    ref, noise, ref_s = c.reference(cfg.reference_passes)
    if progress:
        progress.advance(1)
    rows = []
    for v in cfg.variants:
        rows.append(c.measure(v, ref, noise, cfg.budget_seconds, cfg.trials))
        if progress:
            progress.advance(1)
    return write_comparison(exp, folder, ref, noise, ref_s, rows)


def check_comparison(exp: Experiment):
    """The experiment's ``compare:`` section, or a one-line error."""
    cfg = exp.compare
    if cfg is None:
        raise PsdrError(f"{exp.file}: compare: missing (expected variants: [{{label: ..., guiding: ...}}, ...])")
    if exp.parameter is None:
        raise PsdrError(f"{exp.file}: parameter: missing (compare needs the scalar θ of the gradient)")
    if cfg.view >= len(exp.scene.cameras):
        raise PsdrError(f"{exp.file}: compare.view: view {cfg.view} does not exist (0..{len(exp.scene.cameras) - 1})")
    return cfg


def write_comparison(exp: Experiment, folder: Path, ref, noise: float, ref_s: float, rows: list) -> CompareResult:
    """The files of a comparison (one EXR per variant, reference.exr, grid.png, compare.md,
    compare.json) from its reference and rows (the sequential run's or a Ray sweep's)."""
    cfg = exp.compare
    result = CompareResult(folder, rows=list(rows), reference_rel_mse=noise)
    for row in result.rows:
        v = row.variant
        fileio.write_rgb_exr(folder / f"{v.label.replace('/', '_').replace(' ', '_')}.exr", row.image,
                             {"psdr.variant": v.label, "psdr.rel_mse": f"{row.rel_mse:.6g}"})
    fileio.write_rgb_exr(folder / "reference.exr", ref, {"psdr.passes": str(cfg.reference_passes)})
    plots.gradient_grid(folder / "grid.png", ref, [(r.variant.label, r.image, r.rel_mse) for r in result.rows],
                        f"{exp.name}: {'+'.join(cfg.terms)} gradient, "
                        + (f"{cfg.budget_seconds:g} s per variant" if any(v.passes is None for v in cfg.variants)
                           else "equal samples"))
    table = ["| variant | guiding | sampling | sorted | budget | relMSE | passes | build s | build / pass |",
             "|---|---|---|---|---|---:|---:|---:|---:|"]
    for r in result.rows:
        v = r.variant
        table.append(f"| {v.label} | {v.guiding} | {v.sampling} | {'yes' if v.edge_sort else 'no'} | "
                     f"{f'{v.passes} passes' if v.passes else f'{cfg.budget_seconds:g} s'} | {r.rel_mse:.4g} | "
                     f"{int(np.mean(r.passes))} | {r.build_seconds:.2f} | {r.build_over_pass:.1f} |")
    with fileio.atomic_path(folder / "compare.md") as tmp:
        Path(tmp).write_text("\n".join(table) + "\n")
    fileio.write_json(folder / "compare.json", {
        "experiment": str(exp.file), "terms": list(cfg.terms), "view": cfg.view, "budget_seconds": cfg.budget_seconds,
        "trials": cfg.trials, "reference_passes": cfg.reference_passes, "reference_seconds": ref_s,
        "reference_rel_mse": noise,
        "variants": [{"label": r.variant.label, "guiding": r.variant.guiding, "sampling": r.variant.sampling,
                      "edge_sort": r.variant.edge_sort, "fixed_passes": r.variant.passes, "rel_mse": r.rel_mse,
                      "rel_mse_trials": r.rel_mse_trials, "seconds": r.seconds, "passes": r.passes,
                      "build_seconds": r.build_seconds, "pass_seconds": r.pass_seconds, "guides": r.guides}
                     for r in result.rows]})
    return result
