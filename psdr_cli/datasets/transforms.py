"""The single ``transforms.json`` of instant-ngp and nerfstudio.

Intrinsics (``fl_x``, ``fl_y``, ``cx``, ``cy``, ``w``, ``h``, ``k1``–``k4``, ``p1``, ``p2``,
``camera_model``) are read from each frame, else from the top level (per-frame values override).
Focal lengths (at least 1 px): ``fl_x``, else from ``camera_angle_x`` (radians, between 1° and
170°) as (w/2) / tan(angle/2); ``fl_y``, else from ``camera_angle_y`` likewise with h; a missing
one equals the other. ``cx``, ``cy`` default
to w/2, h/2 (pixel-corner origin, as both programs use). ``w`` and ``h`` default to the image's
size and, when given, must equal it.

``camera_model``: absent, PINHOLE, SIMPLE_PINHOLE, SIMPLE_RADIAL, RADIAL or OPENCV (all
perspective: nerfstudio reads the same k1, k2, p1, p2 keys for each); fisheye, equirectangular
and other models, and instant-ngp's ``is_fisheye``, are refused. Distortion: nerfstudio's
radial polynomial is 1 + k1 r² + k2 r⁴ + k3 r⁶ + k4 r⁸; OpenCV's order is (k1, k2, p1, p2, k3)
and has no r⁸ term, so a non-zero ``k4`` is refused.

``transform_matrix`` is camera-to-world in OpenGL camera axes (x right, y up, z backward), as
both programs write it; its y and z columns are flipped to give OpenCV axes. ``mask_path``
(optional, per frame) names a separate mask file, relative to the JSON file's folder.

nerfstudio's ``applied_transform`` (written by ``ns-process-data``) is the world transform A
it applied to the reconstruction's poses (c2w_file = A · c2w_original). It is undone, c2w =
A⁻¹ · c2w_file, so that the cameras are in the world of the reconstruction they came from (the
COLMAP model beside it); ``undo_applied_transform=False`` keeps the file's world. instant-ngp's
``scale``, ``offset`` and ``aabb_scale`` (applied by instant-ngp when it loads the file) are
ignored: the cameras are in the file's own world.

Splits: nerfstudio's optional ``train_filenames``, ``val_filenames``, ``test_filenames`` (lists
of file paths) give each listed frame its split; a frame listed nowhere is 'train' when there is
no ``train_filenames`` list, else refused. Without these lists every frame is 'train' (the caller
holds out frames itself).
"""
from __future__ import annotations

from functools import partial
from pathlib import Path

import numpy as np

from .frames import (
    SPLITS,
    DatasetError,
    Frame,
    MissingImage,
    check_same_size,
    distortion_tuple,
    focal_from_fov,
    frames_with_images,
    opengl_to_opencv,
    principal_coordinate,
    rigid_matrix,
)
from .images import has_alpha, image_dimensions
from .jsonfile import field_of_view, focal_length, frame_list, image_path, number, read_json, relative_path

FILE_NAME = "transforms.json"

#: nerfstudio camera models that are perspective with (k1, k2, p1, p2) distortion.
PERSPECTIVE_MODELS = ("PINHOLE", "SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")

#: Keys that may be given per frame or at the top level.
INTRINSIC_KEYS = ("fl_x", "fl_y", "cx", "cy", "w", "h", "camera_angle_x", "camera_angle_y",
                  "k1", "k2", "k3", "k4", "p1", "p2", "camera_model", "is_fisheye")


def transforms_file(path) -> Path:
    """``path`` itself when it is a file, else ``<path>/transforms.json``."""
    path = Path(path)
    return path / FILE_NAME if path.is_dir() else path


def read_transforms(path, *, undo_applied_transform: bool = True) -> list[Frame]:
    """The frames of a transforms.json file (or of the folder holding one)."""
    file = transforms_file(path)
    data = read_json(file)
    entries = frame_list(data, file)
    listed = listed_splits(data, file)
    world = world_fix(data, file) if undo_applied_transform else np.eye(4)
    frames = frames_with_images(file, [partial(transforms_frame, file, data, i, entry, world, listed)
                                       for i, entry in enumerate(entries)])
    names = {f.name for f in frames} | {f.image.relative_to(file.parent).as_posix() for f in frames} | \
        {relative_path(e["file_path"], file, f"frames[{i}].file_path") for i, e in enumerate(entries)}  # skipped too
    for key, (name, _) in listed.items():
        if name not in names:
            raise DatasetError(file, key, f"'{name}' names no frame's file_path (expected the path of a listed frame)")
    return check_same_size(frames)


def listed_splits(data: dict, file: Path) -> dict:
    """{'val_filenames[2]': (normalised path, 'val'), ...} from nerfstudio's split lists."""
    listed, seen = {}, {}
    for split in SPLITS:
        key = f"{split}_filenames"
        if key not in data:
            continue
        names = data[key]
        if not isinstance(names, list):
            raise DatasetError(file, key, "expected a list of image file paths")
        for j, value in enumerate(names):
            name = relative_path(value, file, f"{key}[{j}]")
            if name in seen:
                raise DatasetError(file, f"{key}[{j}]",
                                   f"'{name}' is also in {seen[name]} (expected one split per frame)")
            seen[name] = key
            listed[f"{key}[{j}]"] = (name, split)
    return listed


def frame_split(name: str, image_rel: str, data: dict, listed: dict, file: Path, key: str) -> str:
    """The split of a frame by the split lists (see the module docstring)."""
    for listed_name, split in listed.values():
        if listed_name in (name, image_rel):
            return split
    if "train_filenames" in data:
        raise DatasetError(file, key, "is in none of train_filenames, val_filenames, test_filenames "
                                      "(expected every frame in one split list)")
    return "train"


def world_fix(data: dict, file: Path) -> np.ndarray:
    """A⁻¹ for nerfstudio's ``applied_transform`` A (3×4 or 4×4, rigid), else the identity."""
    if "applied_transform" not in data:
        return np.eye(4)
    return np.linalg.inv(rigid_matrix(data["applied_transform"], file, "applied_transform"))


def setting(entry: dict, data: dict, key: str):
    """The frame's value of ``key``, else the top level's, else None."""
    return entry[key] if key in entry else data.get(key)


def transforms_frame(file: Path, data: dict, i: int, entry: dict, world: np.ndarray, listed: dict) -> Frame:
    """One frame: its image, mask, camera and intrinsics."""
    for key in ("file_path", "transform_matrix"):
        if key not in entry:
            raise DatasetError(file, f"frames[{i}].{key}", "missing (expected file_path and transform_matrix)")
    rel = relative_path(entry["file_path"], file, f"frames[{i}].file_path")
    where = f"frames[{i}] ({rel})"
    image = image_path(file.parent, rel, file, where)
    mask = None
    if entry.get("mask_path") is not None:
        mask_rel = relative_path(entry["mask_path"], file, f"frames[{i}].mask_path")
        try:
            mask = image_path(file.parent, mask_rel, file, f"frames[{i}].mask_path")
        except MissingImage as exc:  # a missing mask is an error, not a frame to skip
            raise DatasetError(file, exc.where, exc.message) from None
    c2w = world @ rigid_matrix(entry["transform_matrix"], file, f"frames[{i}].transform_matrix")
    check_model(entry, data, file, i)
    width, height = image_size_checked(entry, data, image, file, i, where)
    fx, fy = focal_lengths(entry, data, file, i, width, height)
    cx, cy = (principal_coordinate(number(setting(entry, data, k), file, named), size, file, named)
              if setting(entry, data, k) is not None else 0.5 * size
              for k, size, named in (("cx", width, key_of(entry, "cx", i)), ("cy", height, key_of(entry, "cy", i))))
    split = frame_split(rel, image.relative_to(file.parent).as_posix(), data, listed, file, where)
    return Frame(name=rel, image=image, mask=mask, cam_to_world=opengl_to_opencv(c2w), fx=fx, fy=fy, cx=cx, cy=cy,
                 width=width, height=height, distortion=distortion(entry, data, file, i), split=split, source=file,
                 has_alpha=has_alpha(image))


def check_model(entry: dict, data: dict, file: Path, i: int):
    """Refuse a camera model that is not perspective (see :data:`PERSPECTIVE_MODELS`)."""
    model = setting(entry, data, "camera_model")
    where = "camera_model" if "camera_model" not in entry else f"frames[{i}].camera_model"
    if model is not None and model not in PERSPECTIVE_MODELS:
        raise DatasetError(file, where, f"{model!r} is not supported (expected {', '.join(PERSPECTIVE_MODELS)})")
    if setting(entry, data, "is_fisheye"):
        raise DatasetError(file, "is_fisheye", "fisheye cameras are not supported (expected a perspective camera)")


def image_size_checked(entry: dict, data: dict, image: Path, file: Path, i: int, where: str) -> tuple[int, int]:
    """The image's (width, height) from its header, equal to ``w``, ``h`` when they are given."""
    width, height = image_dimensions(image, file, where)
    for key, actual in (("w", width), ("h", height)):
        value = setting(entry, data, key)
        if value is not None and number(value, file, key, positive=True) != actual:
            raise DatasetError(file, where, f"image {image} is {width}×{height}, but {key} = {value} "
                                            f"(expected w and h to be the image's size)")
    return width, height


def key_of(entry: dict, key: str, i: int) -> str:
    """How messages name ``key`` of frame ``i``: ``frames[i].key`` when the frame gives it, else the
    top-level ``key``."""
    return f"frames[{i}].{key}" if key in entry else key


def focal_lengths(entry: dict, data: dict, file: Path, i: int, width: int, height: int) -> tuple[float, float]:
    """(fx, fy) by the rules of the module docstring."""
    def named(key):
        return key_of(entry, key, i)

    def focal(key, angle_key, size):
        if setting(entry, data, key) is not None:
            return focal_length(setting(entry, data, key), file, named(key))
        if setting(entry, data, angle_key) is not None:
            return focal_from_fov(size, field_of_view(setting(entry, data, angle_key), file, named(angle_key)))
        return None

    fx, fy = focal("fl_x", "camera_angle_x", width), focal("fl_y", "camera_angle_y", height)
    if fx is None and fy is None:
        raise DatasetError(file, f"frames[{i}]",
                           "no focal length (expected fl_x, fl_y, camera_angle_x or camera_angle_y)")
    return (fx if fx is not None else fy), (fy if fy is not None else fx)


def distortion(entry: dict, data: dict, file: Path, i: int) -> tuple:
    """OpenCV's (k1, k2, p1, p2[, k3]) from nerfstudio's k1, k2, k3, k4, p1, p2; () when all are
    zero. A non-zero k4 (an r⁸ term) has no OpenCV counterpart and is refused."""
    values = {}
    for key in ("k1", "k2", "k3", "k4", "p1", "p2"):
        value = setting(entry, data, key)
        values[key] = 0.0 if value is None else number(value, file, key)
    if values["k4"]:
        raise DatasetError(file, "k4", f"{values['k4']} is not supported (expected 0: OpenCV's model has no r⁸ term)")
    return distortion_tuple(values["k1"], values["k2"], values["p1"], values["p2"], values["k3"])
