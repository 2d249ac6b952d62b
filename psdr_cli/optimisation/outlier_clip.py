"""Owns the clipping of gradient spikes against Adam's running norm (``optimize.outlier_clip``).
Reads the optimiser's state and the unknowns' gradients; writes those gradients.

Before each step the gradient g of each unknown is scaled down to at most c times its usual norm:

    g ← g · min(1, c·√S / ‖g‖),   S = Σ_i v_i / (1 − β₂ᵗ)

with v Adam's second-moment estimate before this step (Σ_i v_i is the running mean of ‖g‖²), t
its step count and c the factor, from step ``WARMUP`` on. ``auto`` clips from path depth
``AUTO_DEPTH``, where the interior term's surface-to-surface segments give an unbiased estimate
with a heavy tail (docs/optimize.md, "Outlier clipping at depth ≥ 3"). The estimators and
``psdr grad`` never clip."""
from __future__ import annotations

import drjit as dr
import numpy as np

WARMUP = 10        # Adam steps before the running norm is trusted
AUTO_FACTOR = 3.0  # c of ``auto``
AUTO_DEPTH = 3     # ``auto`` clips from this path depth on (surface-to-surface segments)


def clip_factor(setting, max_depth: int) -> float | None:
    """c of ``optimize.outlier_clip``: ``auto`` gives AUTO_FACTOR when the paths have a surface-to-
    surface segment (``max_depth`` ≥ AUTO_DEPTH) and no clipping otherwise; ``off`` none; a number
    itself."""
    if setting == "auto":
        return AUTO_FACTOR if max_depth >= AUTO_DEPTH else None
    return None if setting == "off" else float(setting)


def clip_outliers(opt, factor: float | None) -> int:
    """Scales the gradient of each unknown of the Adam optimiser ``opt`` down to factor·√S
    (module docstring); returns how many unknowns were clipped."""
    if factor is None:
        return 0
    clipped = 0
    for key, (_, _, _, extra) in opt.state.items():
        t, v = int(np.asarray(extra[0]).ravel()[0]), np.asarray(extra[2], np.float64)
        if t < WARMUP or v.size == 0:
            continue
        bound = factor * float(np.sqrt(v.sum() / (1.0 - opt.beta_2 ** t)))
        g = dr.grad(opt[key])
        norm = float(np.linalg.norm(np.asarray(g, np.float64)))
        if norm > bound > 0:
            clipped += 1
            dr.set_grad(opt[key], g * (bound / norm))
    return clipped
