"""The starting light of a capture without a light probe (``optimize.envmap`` on a camera dataset
whose experiment gives no ``envmap`` emitter: :func:`psdr_cli.experiment.dataset_frame.unknown_environment`).

The map starts constant, at the radiance under which the object's starting albedo a reproduces
the photographs' mean brightness: a convex diffuse surface under a constant environment L has
radiance a·L, so

    L_0 = B / a,   B = Σ_v Σ_p α_v(p) C_v(p) / Σ_v Σ_p α_v(p)   (per channel),

B the photographs' mean straight colour C inside their masks α (the fitted targets are α·C when
the background is hidden, C when it is visible; without masks, the mean over the whole images), a
the mean of ``optimize.albedo.init``, else of the object's constant reflectance or base colour,
else 0.5. The scale of light × albedo is then settled by ``optimize.envmap.mean``: ``auto`` holds
the map's mean at L_0 while the albedo is an unknown too, so the albedo takes the rest.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

#: The albedo a capture's light is scaled for when neither the experiment nor the BSDF gives one.
DEFAULT_ALBEDO = 0.5


def without_probe(exp) -> bool:
    """Whether ``exp`` recovers an environment that no file gives a start (no ``init``)."""
    env = exp.optimize.envmap
    return env is not None and env.init is None and env.init_file is None and \
        any(e.type == "envmap" and e.file is None for e in exp.scene.emitters)


def photograph_brightness(targets, masks, premultiplied: bool = True) -> np.ndarray:
    """B (3,): the photographs' mean straight colour inside their masks (module docstring);
    ``premultiplied``: the targets are α·C (the background hidden), else C."""
    flat = [np.asarray(t, np.float64).reshape(-1, 3) for t in targets]
    if masks is None:
        return sum(t.sum(0) for t in flat) / sum(len(t) for t in flat)
    alpha = [np.asarray(m, np.float64).reshape(-1, 1) for m in masks.masks]
    total = sum(t.sum(0) if premultiplied else (a * t).sum(0) for t, a in zip(flat, alpha))
    return total / max(sum(float(a.sum()) for a in alpha), 1e-12)


def starting_albedo(exp) -> float:
    """a: the mean of ``optimize.albedo.init``, else of the object's constant reflectance or base
    colour, else :data:`DEFAULT_ALBEDO`."""
    if exp.optimize.albedo_init is not None:
        return float(np.mean(exp.optimize.albedo_init))
    obj = next(o for o in exp.scene.objects if o.name == exp.optimize.object)
    for key in ("reflectance", "base_color"):
        value = obj.bsdf.params.get(key)
        if isinstance(value, (int, float)) or (isinstance(value, (tuple, list)) and len(value) == 3):
            return float(np.mean(value))
    return DEFAULT_ALBEDO


def with_photograph_light(exp, targets, masks):
    """``exp`` with ``optimize.envmap.init`` = L_0 when :func:`without_probe` (else as it is)."""
    if not without_probe(exp):
        return exp
    brightness = photograph_brightness(targets, masks, premultiplied=exp.scene.hide_background)
    start = brightness / max(starting_albedo(exp), 1e-3)
    start = np.maximum(start, 1e-4)
    envmap = replace(exp.optimize.envmap, init=tuple(float(x) for x in start))
    return replace(exp, optimize=replace(exp.optimize, envmap=envmap))
