"""The NeRF-synthetic ("Blender") format: a folder with ``transforms_train.json``,
``transforms_val.json`` and ``transforms_test.json`` (any of them), one per split.

Each file holds ``camera_angle_x``, the horizontal field of view in radians (between 1° and
170°), and ``frames``, each with ``file_path`` (relative to the folder, ``./`` allowed, the
extension optional: .png by default) and ``transform_matrix``, the camera-to-world matrix in OpenGL camera axes (x
right, y up, z backward), turned into OpenCV axes by flipping its y and z columns. The image
size comes from each image's header; pixels are square and the principal point is the image
centre: fx = fy = (W/2) / tan(camera_angle_x / 2), cx = W/2, cy = H/2 (pixel-corner origin).
The images are RGBA PNGs whose alpha is the mask (so ``mask`` is None).
"""
from __future__ import annotations

from functools import partial
from pathlib import Path

from .frames import (SPLITS, DatasetError, Frame, check_same_size, focal_from_fov, frames_with_images, opengl_to_opencv,
                     rigid_matrix)
from .images import has_alpha, image_dimensions
from .jsonfile import field_of_view, frame_list, image_path, read_json, relative_path


def split_file(folder: Path, split: str) -> Path:
    """``<folder>/transforms_<split>.json``."""
    return Path(folder) / f"transforms_{split}.json"


def is_split_file(path: Path) -> bool:
    """Whether ``path`` is named like a split file, ``transforms_<split>.json``."""
    return Path(path).name in {f"transforms_{s}.json" for s in SPLITS}


def is_blender(folder: Path) -> bool:
    """Whether ``folder`` holds at least one ``transforms_<split>.json``."""
    return any(split_file(folder, s).is_file() for s in SPLITS)


def read_blender(folder) -> list[Frame]:
    """The frames of every split file present in ``folder`` (or in the folder of the split file
    ``folder``), in the order train, val, test."""
    folder = Path(folder).parent if is_split_file(folder) and Path(folder).is_file() else Path(folder)
    if not folder.is_dir():
        raise DatasetError(folder, "", "not a folder (expected a Blender dataset with transforms_train.json)")
    files = [(s, split_file(folder, s)) for s in SPLITS if split_file(folder, s).is_file()]
    if not files:
        raise DatasetError(folder, "", "no transforms_train.json, transforms_val.json or transforms_test.json "
                                       "(expected a Blender / NeRF-synthetic dataset)")
    frames = [f for split, file in files for f in read_split(folder, file, split)]
    return check_same_size(frames)


def read_split(folder: Path, file: Path, split: str) -> list[Frame]:
    """The frames of one split file."""
    data = read_json(file)
    if "camera_angle_x" not in data:
        raise DatasetError(file, "camera_angle_x", "missing (expected the horizontal field of view in radians)")
    fov = field_of_view(data["camera_angle_x"], file, "camera_angle_x")
    return frames_with_images(file, [partial(blender_frame, folder, file, split, i, entry, fov)
                                     for i, entry in enumerate(frame_list(data, file))])


def blender_frame(folder: Path, file: Path, split: str, i: int, entry: dict, fov: float) -> Frame:
    """One frame of a split file: its image (size from the header) and its camera."""
    for key in ("file_path", "transform_matrix"):
        if key not in entry:
            raise DatasetError(file, f"frames[{i}].{key}", "missing (expected file_path and transform_matrix)")
    rel = relative_path(entry["file_path"], file, f"frames[{i}].file_path")
    key = f"frames[{i}] ({rel})"
    image = image_path(folder, rel, file, key)
    c2w = rigid_matrix(entry["transform_matrix"], file, f"frames[{i}].transform_matrix")
    width, height = image_dimensions(image, file, key)
    focal = focal_from_fov(width, fov)
    return Frame(name=rel, image=image, mask=None, cam_to_world=opengl_to_opencv(c2w),
                 fx=focal, fy=focal, cx=0.5 * width, cy=0.5 * height, width=width, height=height,
                 distortion=(), split=split, source=file, has_alpha=has_alpha(image))
