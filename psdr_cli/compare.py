"""Equal-time and equal-sample comparisons of boundary estimators (``psdr compare``).

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
from dataclasses import dataclass, field

import numpy as np


def rel_mse(g, ref) -> float:
    return float(((g - ref) ** 2).sum() / max((ref ** 2).sum(), 1e-30))


@dataclass
class Variant:
    label: str
    guiding: str = "none"
    sampling: str = "mis"
    edge_sort: bool = False
    passes: int | None = None   # fixed passes (equal samples); None: the time budget


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
        return self.build_seconds / self.pass_seconds if self.variant.guiding != "none" else 0.0


class Comparison:
    """One scene and view: the experiment, its Mitsuba scene and edge lists (unsorted, sorted)."""

    def __init__(self, exp, terms=("direct",), view: int = 0):
        from . import api
        self.exp, self.terms, self.view = exp, tuple(terms), view
        self.scene, self.parameter, _, _ = api.prepare_gradient(exp)
        self.edges = {s: api.edge_list(self.scene, exp.estimator, s) for s in (False, True)}

    def settings(self, variant: Variant, seed: int):
        from . import api
        from .gradient import Settings
        exp = api.with_estimator(self.exp, guiding=variant.guiding, sampling=variant.sampling,
                                 edge_sort=variant.edge_sort)
        st = Settings.from_experiment(exp)
        st.seed = seed
        return st

    def guides(self, variant: Variant, seed: int):
        """(guides, build seconds) for the variant (empty and 0 without guiding)."""
        from .gradient import make_guides
        t0 = time.perf_counter()
        g = make_guides(self.scene, self.edges[variant.edge_sort], [self.view], self.terms,
                        self.settings(variant, seed))
        return g, time.perf_counter() - t0

    def pass_settings(self, variant: Variant, seed: int, term: str, n: int):
        """Settings of ``n`` passes of ``term``: its per-pass sample count times ``n``
        (a fresh copy per term, so the terms' counts do not compound)."""
        st = self.settings(variant, seed)
        st.passes = n
        if term == "interior":
            st.spp *= n
        elif term == "primary":
            st.primary_spp *= n
        else:
            st.boundary_spp *= n
        return st

    def passes(self, variant: Variant, seed: int, n: int, guides):
        """(mean image over n passes of boundary_spp, per-pass images, seconds)."""
        from .gradient import forward_gradient
        total, images, seconds = None, [], 0.0
        for term in self.terms:
            st = self.pass_settings(variant, seed, term, n)
            est = forward_gradient(self.scene, self.edges[variant.edge_sort], self.parameter, self.view, term, st,
                                   n, guides=guides)
            images = est.passes if not images else [a + b for a, b in zip(images, est.passes)]
            total = est.gradient if total is None else total + est.gradient
            seconds += est.seconds
        return total, images, seconds

    def reference(self, passes: int):
        """(image, its own expected relMSE, seconds): unguided MIS with ``passes`` passes."""
        ref, images, seconds = self.passes(Variant("reference"), 99, passes, None)
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
        self.trial(Variant(variant.label, variant.guiding, variant.sampling, variant.edge_sort, 1), 7, 0.0)
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
