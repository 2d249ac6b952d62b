"""The primary samples a boundary term's passes drew, kept so that the next guide can be fitted
from them (guides fed by the optimisation loop, docs/guiding.md "Guides fed by the loop").

A pass of the direct term draws N primary samples u = (u1, u2) ∈ [0,1)³ of each technique from
its density g (g = 1 unguided) and evaluates the integrand's size F̃(u) = max_RGB |F(u)| (the
guide target without the velocity, docs/theory.md §5) on the way to its image. A
:class:`SampleLog` is a technique → guide mapping, read by the estimator like a plain dict, that
also keeps (u, F̃(u), g(u)) of the passes drawn with it. All passes of one log use the same
guides, so over passes p of N_p samples the deterministic-mixture weight of a sample is
w(u) = 1 / (Σ_p N_p · g(u)), and Σ_{u∈B} w F̃ estimates ∫_B F̄ without bias (F̄ the mean of the
passes' integrands, one view each).

Each pass keeps at most ``per_pass`` samples: of its a samples with F̃ > 0 and b with F̃ = 0 it
keeps the first z = min(b, max(per_pass/4, per_pass − a)) zeros and the first k = min(a,
per_pass − z) others, and scales their weights by b/z and a/k. The lanes of a pass are
independent draws, so the first k of them are a uniform random subset and the box sums stay
unbiased; no random numbers are drawn, so a resumed run keeps the same samples.
"""
from __future__ import annotations

import numpy as np

#: samples kept per pass and technique unless the log is given another budget
PER_PASS = 2048


def thinned(f: np.ndarray, per_pass: int):
    """(indices kept, weight factor of each) of one pass's target values ``f`` (module docstring)."""
    nonzero = np.flatnonzero(f > 0)
    zero = np.flatnonzero(~(f > 0))
    z = min(len(zero), max(per_pass // 4, per_pass - len(nonzero)))
    k = min(len(nonzero), per_pass - z)
    keep = np.r_[nonzero[:k], zero[:z]]
    factor = np.r_[np.full(k, len(nonzero) / max(k, 1)), np.full(z, len(zero) / max(z, 1))]
    return keep, factor


class SampleLog(dict):
    """technique → guide (absent: uniform), plus the samples of the passes drawn with them:
    per technique u (M,3), F̃ (M,) and r = (thinning factor)/g(u) (M,) as float32, and the
    number of samples the passes drew."""

    def __init__(self, guides=None, per_pass: int = PER_PASS):
        super().__init__(guides or {})
        self.per_pass = per_pass
        self.kept: dict = {}
        self.drawn: dict = {}

    def record(self, technique: str, u1, u2, size, g):
        """Keep (a thinned subset of) one pass's samples of ``technique``."""
        u = np.stack([np.asarray(u1), np.asarray(u2.x), np.asarray(u2.y)], axis=1).astype(np.float32)
        n = len(u)
        f = np.broadcast_to(np.asarray(size, np.float32), (n,))
        f = np.where(np.isfinite(f), f, np.float32(0.0))  # a NaN sample says nothing about F̃
        g = np.broadcast_to(np.asarray(g, np.float32), (n,))
        keep, factor = thinned(f, self.per_pass)
        r = factor / g[keep]
        part = (u[keep], f[keep], np.where(np.isfinite(r), r, 0.0).astype(np.float32))
        self.kept.setdefault(technique, []).append(part)
        self.drawn[technique] = self.drawn.get(technique, 0) + n

    def samples(self, technique: str):
        """(u (M,3), F̃ (M,), w (M,)) in float64 with w = r / Σ_p N_p; None when nothing is kept."""
        parts = self.kept.get(technique)
        if not parts:
            return None
        u = np.concatenate([p[0] for p in parts]).astype(np.float64)
        f = np.concatenate([p[1] for p in parts]).astype(np.float64)
        r = np.concatenate([p[2] for p in parts]).astype(np.float64)
        return u, np.where(np.isfinite(f), f, 0.0), r / self.drawn[technique]

    def arrays(self) -> dict:
        """The kept samples as flat arrays ``{technique}_{u,f,r,n}`` (for a saved state)."""
        out = {}
        for t, parts in self.kept.items():
            for i, name in enumerate("ufr"):
                out[f"{t}_{name}"] = np.concatenate([p[i] for p in parts])
            out[f"{t}_n"] = np.array([self.drawn[t]], np.int64)
        return out

    def restore(self, arrays: dict):
        """Samples saved by :meth:`arrays` (one part per technique)."""
        for key in arrays:
            if key.endswith("_n"):
                t = key[:-2]
                self.kept[t] = [tuple(np.asarray(arrays[f"{t}_{name}"], np.float32) for name in "ufr")]
                self.drawn[t] = int(np.ravel(arrays[key])[0])
