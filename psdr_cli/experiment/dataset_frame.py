"""The scene of a camera dataset (``optimize.target.dataset``): its cameras and film, in a frame
where the object has about unit size.

Datasets come in any scale and offset, while psdr's defaults (the initial sphere, λ, the
learning rate) assume an object of about unit size near the origin. The *normalised frame* is
the similarity

    x_n = s · (x − c),

with c the point closest, in the least-squares sense, to every camera's optical axis (the
cameras' common look-at point) and s = 1 / (d · tan(φ/2)), d the median distance of the cameras
from c and φ their median horizontal field of view: the frame's unit is the half-width of the
median view at the object. Everything the experiment's ``scene`` names (area lights, other
objects) is given in the dataset's coordinates and is mapped with the same similarity; an
environment map keeps its orientation in the dataset's world (a similarity has no rotation), its
zenith along the world's up axis (``dataset.up``, or found from the cameras: :func:`world_up`). Meshes are written back with
x = c + x_n / s. Both the frame and the cameras are functions of the cameras alone, so a dataset
scaled by k and shifted by t gives the same normalised problem.
"""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from ..config.dataset import DatasetConfig
from ..config.emitters import EmitterConfig
from ..config.experiment_file import Experiment
from ..config.limits import MAX_FILM
from ..config.objects import ObjectConfig, TransformConfig
from ..datasets.images import has_alpha
from ..datasets.views import read_frames, split_views, view_intrinsics
from ..errors import PsdrError
from ..scene.pinhole import pinhole_camera


def look_at_point(origins: np.ndarray, axes: np.ndarray) -> np.ndarray:
    """c = argmin Σ_i ‖(I − a_i a_iᵀ)(c − o_i)‖², the point closest to every optical axis
    (o_i, a_i); ``None`` when the axes are (nearly) parallel and no such point is defined. (The
    axes' direction does not enter: :func:`normalisation` checks the cameras face the point.)"""
    A, b = np.zeros((3, 3)), np.zeros(3)
    for o, a in zip(origins, axes):
        P = np.eye(3) - np.outer(a, a)
        A += P
        b += P @ o
    w = np.linalg.eigvalsh(A)
    if w[0] < 1e-6 * len(origins):
        return None
    return np.linalg.solve(A, b)


def normalisation(frames, where: str) -> tuple:
    """(s, c) of the normalised frame x_n = s·(x − c) of ``frames`` (module docstring)."""
    origins = np.array([f.cam_to_world[:3, 3] for f in frames])
    axes = np.array([f.cam_to_world[:3, 2] / np.linalg.norm(f.cam_to_world[:3, 2]) for f in frames])
    c = look_at_point(origins, axes)
    if c is None:
        raise PsdrError(f"{where}: the cameras' optical axes are parallel: they have no common look-at point "
                        f"to centre the reconstruction on")
    ahead = np.einsum("ij,ij->i", c - origins, axes) > 0
    if ahead.mean() < 0.5:
        raise PsdrError(f"{where}: the cameras look away from their axes' common point ({int((~ahead).sum())} of "
                        f"{len(ahead)} have it behind them): an object-centred capture is expected (check the "
                        f"camera convention: OpenCV for COLMAP, OpenGL for transforms.json)")
    d = float(np.median(np.linalg.norm(origins - c, axis=1)))
    tan_half = float(np.median([f.width / (2 * f.fx) for f in frames]))
    if not d > 0:
        raise PsdrError(f"{where}: every camera sits at the cameras' common look-at point")
    return 1.0 / (d * tan_half), tuple(float(x) for x in c)


def to_normalised(V, frame: tuple) -> np.ndarray:
    """x_n = s·(x − c) of points ``V`` (n, 3), ``frame`` = (s, c)."""
    s, c = frame
    return s * (np.asarray(V, np.float64) - np.asarray(c))


def to_dataset(V, frame: tuple | None) -> np.ndarray:
    """x = c + x_n / s, the dataset's coordinates of normalised points (unchanged without a frame)."""
    if frame is None:
        return np.asarray(V)
    s, c = frame
    return np.asarray(V, np.float64) / s + np.asarray(c)


def normalised_camera(view, frame: tuple):
    """The :class:`~psdr_cli.config.CameraConfig` of a pinhole view in the normalised frame (the
    rotation is kept, the position mapped)."""
    M = np.array(view.cam_to_world, np.float64)
    M[:3, 3] = to_normalised(M[:3, 3], frame)
    try:
        return pinhole_camera(M, view.fx, view.fy, view.cx, view.cy, view.width, view.height)
    except ValueError as exc:
        raise PsdrError(f"{view.name}: {exc}") from None


def world_up(frames, given=None) -> tuple:
    """The dataset world's up axis: ``given``, else the mean of the cameras' up vectors −R·[0,1,0]
    (people hold cameras upright), snapped to the nearest coordinate axis when within 15° of it."""
    if given is not None:
        up = np.asarray(given, np.float64)
        return tuple(up / np.linalg.norm(up))
    up = -np.mean([f.cam_to_world[:3, 1] for f in frames], axis=0)
    if np.linalg.norm(up) < 1e-6:
        return (0.0, 0.0, 1.0)
    up = up / np.linalg.norm(up)
    k = int(np.argmax(np.abs(up)))
    if abs(up[k]) >= np.cos(np.radians(15)):
        up = np.eye(3)[k] * np.sign(up[k])
    return tuple(float(x) for x in up)


def normalised_emitter(em: EmitterConfig, frame: tuple, up=(0.0, 0.0, 1.0)) -> EmitterConfig:
    """An emitter mapped into the normalised frame: an area light's centre and size; an
    environment map's zenith turned to the world's ``up``; other lights at infinity unchanged."""
    if em.type == "envmap":
        return replace(em, up=tuple(up))
    if em.type != "area":
        return em
    s, _ = frame
    return replace(em, center=tuple(to_normalised(em.center, frame)), size=tuple(s * x for x in em.size))


def normalised_object(obj: ObjectConfig, frame: tuple, reconstructed: str) -> ObjectConfig:
    """An object mapped into the normalised frame: s·(T R S x − c) = s(t − c) + R (sS) x. The
    reconstructed object is a placeholder (its shape comes from ``optimize.init``) and is left as is."""
    if obj.name == reconstructed:
        return obj
    s, _ = frame
    t = obj.transform
    moved = TransformConfig(translate=tuple(to_normalised(t.translate, frame)), rotate_axis=t.rotate_axis,
                            rotate_deg=t.rotate_deg, scale=tuple(s * x for x in t.scale))
    return replace(obj, transform=moved)


def dataset_frames(dataset: DatasetConfig, split: str = "train"):
    """The frames of ``split`` ('train', 'test': the held-out views, or 'all') of a dataset, read
    and checked (:func:`psdr_cli.datasets.views.read_frames`); every split is read so that the
    normalised frame does not depend on which is asked for."""
    frames = read_frames(dataset, where="optimize.target.dataset")
    if split == "all":
        return frames, list(frames)
    train, held_out = split_views(frames, dataset.holdout_every, f"{dataset.key}.holdout_every")
    chosen = train if split == "train" else held_out
    if not chosen:
        raise PsdrError(f"{dataset.path}: the dataset has no {'training' if split == 'train' else 'held-out'} views "
                        f"(optimize.target.dataset.holdout_every splits every k-th frame off)")
    return frames, chosen


def dataset_scene(exp: Experiment, split: str = "train") -> Experiment:
    """``exp`` with the cameras and film of a dataset's ``split`` in the normalised frame, the
    scene's lights and objects mapped into it, the frame stored in ``optimize.target_dataset``,
    and the background hidden when the photographs carry masks (``background: auto``). On an
    experiment whose scene is already mapped (``target_dataset.frame`` set: another split of a
    loaded experiment), only the cameras, film and background change."""
    dataset = exp.optimize.target_dataset
    frames, chosen = dataset_frames(dataset, split)
    frame = normalisation(frames, str(dataset.path))
    views = [processed_view(f, dataset.downsample, f"{dataset.key}.downsample") for f in chosen]
    width, height = film_size(views[0], chosen[0], dataset)
    cameras = [normalised_camera(v, frame) for v in views]
    hidden = hides_background(exp, dataset, frames)
    scene = replace(exp.scene, width=width, height=height, cameras=cameras, hide_background=hidden)
    if dataset.frame is None:
        up = world_up(frames, dataset.up)
        emitters = list(exp.scene.emitters) + unknown_environment(exp)
        scene = replace(scene, emitters=[normalised_emitter(e, frame, up) for e in emitters],
                        objects=[normalised_object(o, frame, exp.optimize.object) for o in exp.scene.objects])
    opt = replace(exp.optimize, target_dataset=replace(dataset, frame=frame, split=split))
    return replace(exp, scene=scene, optimize=opt)


def unknown_environment(exp: Experiment) -> list:
    """[the environment emitter a capture without a light probe gets] when ``optimize.envmap`` is
    an unknown and the experiment gives no ``envmap`` emitter (its map is all unknown; its start
    comes from the photographs: :mod:`psdr_cli.optimisation.photo_light`), else []."""
    if exp.optimize.envmap is None or any(e.type == "envmap" for e in exp.scene.emitters):
        return []
    return [EmitterConfig(type="envmap", key="optimize.envmap")]


def hides_background(exp: Experiment, dataset: DatasetConfig, frames) -> bool:
    """Whether camera rays that leave the scene see black: ``background: hidden``, or ``auto``
    with masked photographs (every frame masked, or none: a mix is refused). Refused with it:
    Mitsuba's engine (in the experiment or a variant), which draws the environment, and other
    objects, which would show against the masks' black."""
    masked = [has_mask(f) for f in frames]
    if dataset.background == "auto" and any(masked) and not all(masked):
        bad = next(f for f, m in zip(frames, masked) if not m)
        raise PsdrError(f"{bad.image}: this photograph has no mask (no alpha, no mask file) while others have: "
                        f"give every photograph a mask, or none (optimize.target.dataset.background: visible)")
    hidden = dataset.background == "hidden" or (dataset.background == "auto" and all(masked))
    if not hidden:
        return False
    engines = [exp.estimator.engine] + [v.engine for v in exp.optimize.variants if getattr(v, "engine", None)]
    if "mitsuba" in engines:
        raise PsdrError(f"{exp.file}: estimator.engine: 'mitsuba' cannot hide the background of masked photographs "
                        f"(use the psdr engine, or optimize.target.dataset.background: visible)")
    others = [o.name for o in exp.scene.objects if o.name != exp.optimize.object]
    if others:
        raise PsdrError(f"{exp.file}: scene.objects: '{others[0]}' would show against the black the masked "
                        f"photographs are fitted on: with masks the scene holds only the reconstructed object "
                        f"(or set optimize.target.dataset.background: visible)")
    return True


def film_size(view, frame, dataset: DatasetConfig) -> tuple[int, int]:
    """(width, height) of the film a dataset's ``view`` (of ``frame``) sets, if psdr's film can
    hold it (:data:`~psdr_cli.config.limits.MAX_FILM` per side), else a one-line PsdrError naming
    the photograph, the size its header gives and the downsampling that would fit."""
    if max(view.width, view.height) <= MAX_FILM:
        return view.width, view.height
    factor = dataset.downsample * math.ceil(max(view.width, view.height) / MAX_FILM)
    file, _, key = dataset.key.rpartition(": ")
    raise PsdrError(f"{frame.image}: the photographs are {frame.width}×{frame.height} pixels (by the image header), "
                    f"{view.width}×{view.height} after downsampling by {dataset.downsample}: psdr's film holds at "
                    f"most {MAX_FILM} pixels a side (set {key}.downsample to {factor} or more"
                    f"{f' in {file}' if file else ''})")


def processed_view(frame, k: int, key: str):
    """A frame with the pinhole intrinsics and size of the image psdr fits (undistorted, square
    pixels, downsampled by ``k``, the experiment's ``key``: :func:`psdr_cli.datasets.views.view_intrinsics`)."""
    fx, fy, cx, cy, width, height = view_intrinsics(frame, downsample=k, key=key)
    return replace(frame, fx=fx, fy=fy, cx=cx, cy=cy, width=width, height=height, distortion=())


def has_mask(frame) -> bool:
    """Whether a frame has a mask: a mask file, or an alpha channel in its image."""
    return frame.mask is not None or has_alpha(frame.image)

