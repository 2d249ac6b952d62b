"""The fingerprint of a run (version 2): a hash of what its result depends on, which
``--resume`` compares."""
from __future__ import annotations

import hashlib
import json
from dataclasses import MISSING, fields, is_dataclass

from ..config.experiment_file import Experiment


#: Version of :func:`run_fingerprint`, recorded in run.json next to the fingerprint.
FINGERPRINT_VERSION = 2
#: Optimize keys that only extend or observe a run: changing them continues the same run.
OBSERVING_KEYS = ("iterations", "seconds", "checkpoint_every", "preview_views", "variants")
#: Estimator keys read only by the Mitsuba engine, and only by the psdr engine.
MITSUBA_ONLY_KEYS = ("mitsuba_integrator", "mitsuba_spp", "mitsuba_shadows")
PSDR_ONLY_KEYS = ("primary_sampling",)


def run_fingerprint(exp: Experiment) -> str:
    """Hash of what a run's result depends on: the scene, estimator and optimize sections and the
    seed, written by :func:`non_default` (a key at its default is left out, so a key added with a
    default changes no fingerprint), without the optimize keys that only extend or observe a run
    (:data:`OBSERVING_KEYS`) and the estimator keys the run's engine does not read, with paths
    relative to the experiment's folder. ``--resume`` continues a run only while this is
    unchanged. The contents of mesh and image files are not part of it."""
    est = non_default(exp.estimator)
    for key in MITSUBA_ONLY_KEYS if exp.estimator.engine == "psdr" else PSDR_ONLY_KEYS:
        est.pop(key, None)
    opt = non_default(exp.optimize)
    for key in OBSERVING_KEYS:
        opt.pop(key, None)
    return digest(exp, (scene_identity(non_default(exp.scene)), est, opt))


def scene_identity(d: dict) -> dict:
    """A scene's dict (``asdict`` or :func:`non_default`) with ``mitsuba.resolved: true``, the flag
    an XML scene's source carried once read, before experiments were loaded whole: fingerprints
    and cached targets of runs saved then still match. The XML's meshes as loaded
    (``mitsuba.geometry``) are left out: the XML file and its digest identify them."""
    if d.get("mitsuba"):
        d["mitsuba"] = {**{k: v for k, v in d["mitsuba"].items() if k != "geometry"}, "resolved": True}
    return d


def digest(exp: Experiment, parts) -> str:
    """First 16 hex digits of SHA-256 over the JSON of ``parts`` (the experiment's folder written
    as a placeholder) and the seed."""
    h = hashlib.sha256()
    for part in parts:
        text = json.dumps(part, default=str, sort_keys=True)
        h.update(text.replace(str(exp.base_dir), "<experiment folder>").encode())  # the checkout may move
    h.update(str(exp.seed).encode())
    return h.hexdigest()[:16]


def non_default(value):
    """A config dataclass as a dict without the fields whose value equals the field's default,
    recursively (lists, tuples and dicts of dataclasses included); other values as they are."""
    if is_dataclass(value) and not isinstance(value, type):
        return {f.name: non_default(getattr(value, f.name)) for f in fields(value)
                if not is_default(f, getattr(value, f.name))}
    if isinstance(value, (list, tuple)):
        return [non_default(v) for v in value]
    if isinstance(value, dict):
        return {k: non_default(v) for k, v in value.items()}
    return value


def is_default(f, value) -> bool:
    if f.default is not MISSING:
        default = f.default
    elif f.default_factory is not MISSING:
        default = f.default_factory()
    else:
        return False  # a required field
    return _canonical(value) == _canonical(default)


def _canonical(value) -> str:
    """JSON text of :func:`non_default` of a value (tuples and lists alike), so that arrays and
    nested dataclasses compare by what the fingerprint holds of them."""
    return json.dumps(non_default(value), default=str, sort_keys=True)
