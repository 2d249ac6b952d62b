"""Fingerprint version 1 (run.json without ``fingerprint_version``): read only, kept unchanged
so that such runs can be resumed. It hashes every field that existed in version 1
(:data:`V1_FIELDS`); a field added since is hashed only when it differs from its default."""
from __future__ import annotations

from dataclasses import fields, is_dataclass, replace

from ..config.experiment_file import Experiment
from .fingerprint import digest, is_default, scene_identity


def fingerprint_v1(exp: Experiment) -> str:
    """Version-1 fingerprint: scene, estimator, seed and the optimize section except iterations,
    seconds, checkpoint_every, preview_views and variants (:func:`estimator_identity_v1`,
    :func:`optimize_identity_v1`), paths relative to the experiment's folder."""
    opt = replace(exp.optimize, iterations=0, seconds=None, checkpoint_every=0, preview_views=(), variants=())
    return digest(exp, (scene_identity(_asdict_v1(exp.scene)), estimator_identity_v1(exp.estimator),
                        optimize_identity_v1(opt)))


def optimize_identity_v1(opt) -> dict:
    """Version-1 optimize keys: a single λ as its number, no ``downsample`` when every stage
    renders at full resolution."""
    d = _asdict_v1(opt)
    if len(opt.lambda_) == 1:
        d["lambda_"] = opt.lambda_[0]
    if all(k == 1 for k in opt.downsample):
        d.pop("downsample")
    return d


def estimator_identity_v1(est) -> dict:
    """Version-1 estimator keys: without the engine keys with ``engine: psdr``, without
    ``primary_sampling`` with ``engine: mitsuba`` or ``primary_sampling: length``."""
    d = _asdict_v1(est)
    if est.engine == "psdr":
        for key in ("engine", "mitsuba_integrator", "mitsuba_spp", "mitsuba_shadows"):
            d.pop(key)
    if est.engine == "mitsuba" or est.primary_sampling == "length":
        d.pop("primary_sampling")
    return d


def _asdict_v1(value):
    """``dataclasses.asdict`` without the fields that are not in :data:`V1_FIELDS` and hold their
    default."""
    if is_dataclass(value) and not isinstance(value, type):
        known = V1_FIELDS.get(type(value).__name__, ())
        return {f.name: _asdict_v1(getattr(value, f.name)) for f in fields(value)
                if f.name in known or not is_default(f, getattr(value, f.name))}
    if isinstance(value, (list, tuple)):
        return type(value)(_asdict_v1(v) for v in value)
    if isinstance(value, dict):
        return {k: _asdict_v1(v) for k, v in value.items()}
    return value


#: The fields of the config dataclasses when version 1 was current.
V1_FIELDS = {
    "SceneConfig": ("width", "height", "max_depth", "cameras", "emitters", "objects", "mitsuba"),
    "CameraConfig": ("origin", "target", "up", "fov"),
    "EmitterConfig": ("type", "key", "radiance", "center", "normal", "size", "file", "scale", "rotate_deg",
                      "sun_direction", "turbidity", "albedo", "sun_scale", "sky_scale"),
    "ObjectConfig": ("name", "mesh", "key", "transform", "bsdf", "edges", "smooth", "bsdf_given", "parts"),
    "MeshSpec": ("key", "file", "shape", "params", "repair", "part", "split"),
    "TransformConfig": ("translate", "rotate_axis", "rotate_deg", "scale"),
    "BsdfConfig": ("type", "params"),
    "BitmapConfig": ("file", "filter_type", "wrap_mode", "raw", "data"),
    "MitsubaSource": ("file", "params", "film", "edges", "up", "up_given", "cameras_given", "max_depth_given",
                      "digest", "resolved"),
    "EstimatorConfig": ("spp", "primary_spp", "boundary_spp", "terms", "sampling", "guiding", "passes",
                        "guide_epsilon", "edge_sort", "primary_sampling", "engine", "mitsuba_integrator",
                        "mitsuba_spp", "mitsuba_shadows", "chains", "grid", "kdtree"),
    "ChainConfig": ("max_turn", "max_length"),
    "GridConfig": ("resolution", "samples_per_cell"),
    "KdTreeConfig": ("samples_per_node", "initial_samples", "refine_ratio", "interval_share", "technique_share",
                     "threshold", "max_depth", "max_leaves"),
    "OptimizeConfig": ("object", "target_images", "target_mesh", "target_spp", "init", "init_transform", "remesh",
                       "iterations", "batch_size", "learning_rate", "learning_rate_final", "lambda_", "downsample",
                       "guide_every", "adjoint_spp", "checkpoint_every", "preview_views", "albedo", "albedo_init",
                       "albedo_learning_rate", "albedo_texture", "envmap_rotation", "envmap_axis",
                       "envmap_init_deg", "envmap_learning_rate", "seconds", "variants", "target_seed"),
    "RemeshConfig": ("method", "initial", "at", "vertices"),
    "Variant": ("label", "guiding", "sampling", "edge_sort", "seed", "passes", "engine"),
}
