"""The starting light of a capture without a light probe (``optimize.envmap`` on a camera dataset
whose experiment gives no ``envmap`` emitter: :func:`psdr_cli.dataset_scene.unknown_environment`).

The map starts constant, at the radiance under which the object's starting albedo a reproduces
the photographs' mean brightness: a convex diffuse surface under a constant environment L has
radiance a·L, so

    L_0 = B / a,   B = Σ_v Σ_p T_v(p) / Σ_v Σ_p α_v(p)   (per channel),

B the photographs' mean straight colour inside their masks (T the fitted targets, premultiplied by
the coverage α when the background is hidden; without masks, the mean over the whole images), a
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


def photograph_brightness(targets, masks) -> np.ndarray:
    """B (3,): the photographs' mean straight colour inside their masks (module docstring)."""
    total = sum(np.asarray(t, np.float64).reshape(-1, 3).sum(0) for t in targets)
    if masks is None:
        return total / sum(np.asarray(t).reshape(-1, 3).shape[0] for t in targets)
    covered = sum(float(np.asarray(m, np.float64).sum()) for m in masks.masks)
    return total / max(covered, 1e-12)


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
    start = photograph_brightness(targets, masks) / max(starting_albedo(exp), 1e-3)
    start = np.maximum(start, 1e-4)
    envmap = replace(exp.optimize.envmap, init=tuple(float(x) for x in start))
    return replace(exp, optimize=replace(exp.optimize, envmap=envmap))
