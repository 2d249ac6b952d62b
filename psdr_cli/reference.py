"""Independent references for a gradient image: finite differences and Mitsuba's projective
integrator.

- Central finite differences with common random numbers:
  FD_h = [I(θ + h) − I(θ − h)] / 2h, both renders with the same seed, so most of the Monte Carlo
  noise cancels. Run in ``batches`` independent seeds to give a standard error.
- Mitsuba's ``prb_projective`` (forward mode through ``mi.render``), a different estimator of the
  same derivative, with its guiding switched off (its default guides can give regions zero
  probability).
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from .render import render_view


def finite_difference(scene, parameter, view: int, h: float, spp: int, seed: int = 0,
                      batches: int = 4, progress=None) -> list:
    """Per-batch central differences (H, W, 3) with ``spp`` samples per pixel in total."""
    out = []
    per_batch = max(1, spp // batches)
    for b in range(batches):
        imgs = []
        for sign in (1.0, -1.0):
            parameter.apply(mi.Float(sign * h))
            imgs.append(render_view(scene, view, per_batch, seed=seed * 7919 + 101 + b))
            if progress:
                progress(per_batch)
        parameter.reset()
        out.append((imgs[0].astype(np.float64) - imgs[1]) / (2 * h))
    return out


def mitsuba_projective(scene, parameter, view: int, spp: int, seed: int = 0, max_depth: int | None = None,
                       batches: int = 1) -> list:
    """Per-batch forward-mode gradient images of Mitsuba's ``prb_projective`` (unguided)."""
    max_depth = scene.config.max_depth if max_depth is None else max_depth
    integrator = mi.load_dict({"type": "prb_projective", "max_depth": max_depth, "guiding": "none"})
    params = parameter.params
    out = []
    for b in range(batches):
        theta = mi.Float(0.0)
        dr.enable_grad(theta)
        parameter.apply(theta)
        dr.set_grad(theta, 1.0)
        dr.forward_from(theta, dr.ADFlag.ClearEdges)
        img = mi.render(scene.mi_scene, params, sensor=view, integrator=integrator, spp=spp,
                        seed=seed * 7919 + 977 + b)
        dr.forward_to(img)
        out.append(np.asarray(dr.grad(img), np.float64))
        parameter.reset()
    return out
