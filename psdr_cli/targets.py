"""What an optimisation fits and where it starts: the ground-truth shape, the target images
(rendered once from it and cached in the run folder, EXR files from ``psdr render``, or the
photographs of a camera dataset: :mod:`psdr_cli.dataset_targets`) and the initial shape."""
from __future__ import annotations

import glob
import hashlib
import json
from dataclasses import asdict
from pathlib import Path
from typing import NamedTuple

import numpy as np

from . import atlas, fileio, meshes
from .dataset_scene import to_dataset, to_normalised
from .dataset_targets import TargetMasks, dataset_initial_shape, dataset_masks, dataset_targets
from .errors import PsdrError
from .meshes import object_mesh
from .mitsuba_scene import scene_files
from .remesh import remesh
from .render import camera_header, header_camera, render_view
from .run_folder.checkpoints import write_mesh
from .run_folder.fingerprint import scene_identity
from .run_folder.layout import RunFiles
from .run_folder.state import State
from .run_folder.target_cache import cached_target
from .scene import build_scene


class TargetInputs(NamedTuple):
    """What a run's targets come from: the ``target.images`` (with their cameras), or the ground
    truth (V, F) the targets are rendered from; for a fresh run, its initial shape (V, F, UV or
    None: :func:`initial_shape_uv`); and the targets' (H, W) masks when every photograph of a
    dataset has one (else None)."""
    images: list | None
    cameras: list | None
    reference: tuple | None
    initial: tuple | None = None
    masks: TargetMasks | None = None


def read_targets(exp, fresh: bool = False) -> TargetInputs:
    """:class:`TargetInputs` of a run, read and checked (``preview_views`` included) without
    writing anything: a bad input fails before the run folder is touched. ``fresh``: also the
    initial shape (a resumed run starts from its saved state)."""
    cfg = exp.optimize
    views = len(exp.scene.cameras)
    hull = None
    if cfg.target_dataset:
        images, dataset = dataset_targets(exp)
        inputs, views = TargetInputs(images, None, None, masks=dataset_masks(exp, dataset)), len(images)
        hull = dataset if fresh and cfg.init is None else None
    elif cfg.target_images:
        images, cameras = image_targets(exp)
        inputs, views = TargetInputs(images, cameras, None), len(images)
    else:
        inputs = TargetInputs(None, None, ground_truth(exp))
    bad = [v for v in cfg.preview_views if v >= views]
    if bad:
        raise PsdrError(f"{exp.file}: optimize.preview_views: view {bad[0]} does not exist (0..{views - 1})")
    if hull is not None:
        return inputs._replace(initial=(*dataset_initial_shape(exp, hull), None))
    return inputs._replace(initial=initial_shape_uv(exp, inputs.reference)) if fresh else inputs


def load_targets(exp, files: RunFiles, inputs: TargetInputs):
    """(target images, cameras or None, ground truth (V, F) or None) of a run: the given images,
    or renders of the ground truth (cached in ``targets/``; the ground truth is written to the
    run folder as ``reference.ply``)."""
    if inputs.images is not None:
        return inputs.images, inputs.cameras, None
    write_mesh(files.reference, *inputs.reference)  # the shape this run's targets come from
    return render_targets(exp, files, inputs.reference), None, inputs.reference


def initial_state(exp, files: RunFiles, shape, warn) -> State:
    """The state of a fresh run from its initial shape (V, F, UV or None: :func:`initial_shape_uv`),
    remeshed (``remesh.initial``) unless ``remesh.method: none``, written as checkpoint 0."""
    cfg = exp.optimize
    V, F, uv = shape
    if cfg.remesh.method != "none":
        if uv is not None:  # split at UV seams: the remeshers want one vertex per position
            V, F = meshes.weld_vertices(V, F)
        V, F = remesh(V, F, cfg.remesh.initial, cfg.remesh.method, warn=warn)
        uv = None
        if cfg.albedo and cfg.albedo_texture is not None:  # the texture starts uniform: new UVs suffice
            try:
                V, F, uv = atlas.unwrap(V, F, cfg.albedo_texture)
            except Exception as exc:  # noqa: BLE001 - xatlas failed on the remeshed initial shape
                raise PsdrError(f"{exp.file}: optimize.albedo.texture: no UV atlas for the remeshed initial shape "
                                f"({type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''})") from None
    write_mesh(files.checkpoint(0), dataset_coordinates(exp, V), F)
    return State(0, V, F, uv=uv)


def dataset_coordinates(exp, V):
    """Vertices ``V`` in the coordinates the user gave: a dataset's own (``V`` is in its normalised
    frame: :mod:`psdr_cli.dataset_scene`), else the scene's (unchanged)."""
    dataset = exp.optimize.target_dataset
    return to_dataset(V, dataset.frame if dataset else None)


def ground_truth(exp):
    """World-space (V, F) of the target shape: ``target.mesh`` (placed with the object's
    transform) or the object's own mesh in the scene."""
    cfg = exp.optimize
    obj = next(o for o in exp.scene.objects if o.name == cfg.object)
    if cfg.target_mesh is None:
        return object_mesh(obj, str(exp.file))
    V, F = meshes.load_mesh(cfg.target_mesh, str(exp.file))
    return meshes.apply_transform(V, meshes.transform_matrix(obj.transform)), F


def initial_shape(exp, reference):
    """(V, F) of ``init`` (with its transform), or a sphere around the reference's bounding box."""
    return initial_shape_uv(exp, reference)[:2]


def initial_shape_uv(exp, reference):
    """(V, F, UV or None) of the initial shape (:func:`initial_shape`); with ``albedo.texture`` the
    default sphere is a UV sphere, and a given ``init`` must have UVs. With a camera dataset an
    ``init`` mesh file (and its transform) is in the dataset's coordinates, like the meshes a run
    writes (so a run can start from another's ``final.ply``); a procedural shape is in the
    normalised frame, where the object has about unit size (:mod:`psdr_cli.dataset_scene`)."""
    cfg = exp.optimize
    texture = cfg.albedo and cfg.albedo_texture is not None
    if cfg.init is not None:
        V, F, uv = meshes.load_mesh_uv(cfg.init, str(exp.file), keep_uv=texture)
        if texture and uv is None:
            raise PsdrError(f"{exp.file}: optimize.init.mesh: has no UV coordinates, which optimize.albedo.texture "
                            f"needs (e.g. {{shape: sphere, resolution: 16, uv: true}}, or an OBJ with 'vt')")
        V = meshes.apply_transform(V, meshes.transform_matrix(cfg.init_transform))
        if cfg.target_dataset and cfg.init.file is not None:  # a mesh file is in the dataset's coordinates
            V = to_normalised(V, cfg.target_dataset.frame)
        return V, F, uv
    if reference is None:
        raise PsdrError(f"{exp.file}: optimize.init: required when the targets are images "
                        f"(e.g. init: {{mesh: {{shape: sphere, radius: 0.5}}}})")
    V, F = reference
    lo, hi = V.min(0), V.max(0)
    radius = 0.5 * float((hi - lo).max())
    Vs, Fs, uv = meshes.uv_sphere(radius, 16) if texture else (*meshes.sphere(radius=radius, subdivisions=3), None)
    return Vs + (lo + hi) / 2, Fs, uv


def target_seed(exp) -> int:
    """Seed of the target renders: the experiment's (for a variant, the base experiment's, so
    that every run of an ablation fits the same images)."""
    return exp.seed if exp.optimize.target_seed is None else exp.optimize.target_seed


def input_files(exp) -> list:
    """Every file the experiment's scene reads: those it names (mesh files, textures, environment
    maps, the XML scene) and, for an XML scene, the files the XML names (its includes, meshes,
    textures, environment maps: :func:`psdr_cli.mitsuba_scene.scene_files`)."""
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


def image_targets(exp):
    """(images, cameras) from ``target.images`` (EXR files written by ``psdr render``)."""
    pattern = exp.optimize.target_images
    paths = sorted(glob.glob(pattern))
    if not paths:
        raise PsdrError(f"{exp.file}: optimize.target.images: no file matches '{pattern}'")
    images, cameras = [], []
    for p in paths:
        try:
            exr = fileio.read_exr(p)
            cam = json.loads(exr["__header__"]["psdr.camera"])
        except KeyError:
            raise PsdrError(f"{p}: no 'psdr.camera' header (target images must come from `psdr render`)") from None
        except Exception as exc:  # noqa: BLE001 - unreadable EXR
            raise PsdrError(f"{p}: cannot read the EXR target ({str(exc).splitlines()[0] if str(exc) else exc})") from None
        image = np.stack([exr["R"], exr["G"], exr["B"]], -1).astype(np.float64)
        if image.shape[:2] != (exp.scene.height, exp.scene.width):
            raise PsdrError(f"{p}: image is {image.shape[1]}×{image.shape[0]}, but scene.film is "
                            f"{exp.scene.width}×{exp.scene.height}")
        images.append(image)
        try:
            cameras.append(header_camera(cam))
        except (KeyError, TypeError, ValueError):
            raise PsdrError(f"{p}: its 'psdr.camera' header is not a camera written by `psdr render`") from None
    return images, cameras
