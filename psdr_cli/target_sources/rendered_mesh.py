"""The target source ``mesh``, the default: target images rendered once from the ground-truth
shape (``optimize.target.mesh`` placed with the object's transform, or the object's own mesh) at
``target.spp`` and cached in the run folder's ``targets/`` by a hash of what they depend on; the
ground truth is written to the run folder as ``reference.ply``."""
from __future__ import annotations

import hashlib
import json
from dataclasses import asdict
from pathlib import Path

import numpy as np

from ..rendering.render import camera_header, render_view
from ..run_folder.checkpoints import write_mesh
from ..run_folder.fingerprint import scene_identity
from ..run_folder.layout import RunFiles
from ..run_folder.target_cache import cached_target
from ..scene import meshes
from ..scene.build import build_scene
from ..scene.meshes import object_mesh, xml_geometry
from ..scene.mitsuba_xml import scene_files
from ..support import fileio
from .source import TargetInputs, TargetSource


def ground_truth(exp):
    """World-space (V, F) of the target shape: ``target.mesh`` (placed with the object's
    transform) or the object's own mesh in the scene."""
    cfg = exp.optimize
    obj = next(o for o in exp.scene.objects if o.name == cfg.object)
    if cfg.target_mesh is None:
        return object_mesh(obj, str(exp.file), xml_geometry(exp.scene))
    V, F = meshes.load_mesh(cfg.target_mesh, str(exp.file))
    return meshes.apply_transform(V, meshes.transform_matrix(obj.transform)), F


def target_seed(exp) -> int:
    """Seed of the target renders: the experiment's (for a variant, the base experiment's, so
    that every run of an ablation fits the same images)."""
    return exp.seed if exp.optimize.target_seed is None else exp.optimize.target_seed


def input_files(exp) -> list:
    """Every file the experiment's scene reads: those it names (mesh files, textures, environment
    maps, the XML scene) and, for an XML scene, the files the XML names (its includes, meshes,
    textures, environment maps: :func:`psdr_cli.scene.mitsuba_xml.scene_files`)."""
    found = set()

    def walk(value):
        if isinstance(value, Path):
            found.add(value)
        elif isinstance(value, dict):
            for v in value.values():
                walk(v)
        elif isinstance(value, (list, tuple)):
            for v in value:
                walk(v)

    walk(asdict(exp.scene))
    if exp.scene.mitsuba is not None:
        found.update(scene_files(exp.scene.mitsuba))
    return sorted(p for p in found if p.is_file())


def _scene_dict(scene) -> dict:
    """``asdict`` of the scene without the camera keys added since target keys were introduced
    when they hold their default (``principal_point``, ``hide_background``, an emitter's ``up``), so that cached targets stay valid."""
    d = asdict(scene)
    if not d["hide_background"]:
        del d["hide_background"]
    for em in d["emitters"] or []:
        if tuple(em["up"]) == (0.0, 0.0, 1.0):
            del em["up"]
    for cam in d["cameras"] or []:
        if not any(cam["principal_point"]):
            del cam["principal_point"]
    return d


def target_key(exp, reference, spp: int) -> str:
    """Hash of everything a cached target image depends on: the scene, the ground truth, spp and
    seed, and the contents of every file the scene reads (:func:`input_files`), so that an edited
    mesh file, texture, environment map or included XML file makes new targets."""
    seed, paths = target_seed(exp), input_files(exp)
    h = hashlib.sha256()
    h.update(json.dumps(scene_identity(_scene_dict(exp.scene)), default=str, sort_keys=True).encode())
    h.update(np.ascontiguousarray(reference[0], np.float64).tobytes())
    h.update(np.ascontiguousarray(reference[1], np.int64).tobytes())
    h.update(f"{spp}:{seed}".encode())
    for path in paths:
        h.update(path.read_bytes())
    return h.hexdigest()[:16]


def render_targets(exp, files: RunFiles, reference, progress=None):
    """Target images of every view, rendered from the ground truth at ``target.spp`` and cached
    in ``targets/`` (reused while the scene, the ground truth and spp are unchanged, and only if
    every cached file can be read back whole: see :func:`psdr_cli.run_folder.target_cache.cached_target`)."""
    cfg = exp.optimize
    seed = target_seed(exp) + 7919
    key = target_key(exp, reference, cfg.target_spp)
    paths = [files.targets / f"view_{v:03d}.exr" for v in range(len(exp.scene.cameras))]
    cached = [cached_target(p, key, (exp.scene.height, exp.scene.width)) for p in paths]
    if all(image is not None for image in cached):
        return cached
    scene = build_scene(exp, objects={cfg.object: reference})
    images = []
    for v, p in enumerate(paths):
        image = render_view(scene, v, cfg.target_spp, seed=seed)
        cam = exp.scene.cameras[v]
        fileio.write_rgb_exr(p, image, {"psdr.target_key": key, "psdr.view": str(v), "psdr.spp": str(cfg.target_spp),
                                    "psdr.camera": camera_header(cam)})
        fileio.write_preview(p.with_suffix(".png"), image)
        images.append(image)
        if progress:
            progress(v)
    return images


def read_ground_truth(exp) -> TargetInputs:
    """The ground truth the targets are rendered from (:func:`ground_truth`)."""
    return TargetInputs(None, None, ground_truth(exp))


def load_rendered(exp, files: RunFiles, inputs: TargetInputs) -> list:
    """``reference.ply`` written, and the targets rendered from it (or read from the cache)."""
    write_mesh(files.reference, *inputs.reference)  # the shape this run's targets come from
    return render_targets(exp, files, inputs.reference)


SOURCE = TargetSource("mesh", lambda optimize: True, read_ground_truth, load_rendered)
