"""The entry point of camera datasets: :func:`read_frames` reads the cameras of a dataset in any
supported format into :class:`Frame` records (cheap: images are only opened for their size),
:func:`load_views` decodes their photographs into :class:`View` records, ready to fit, and
:func:`split_views` separates the views (or frames) to fit from those held out.

A dataset ``spec`` is a path, a mapping, or an object with attributes of these names (e.g. the
experiment's dataset section; its ``key``, when it has one, names it in messages):

* ``path``: the dataset folder (or a JSON file in it: ``transforms.json``, or any
  ``transforms_<split>.json``, which stands for its folder);
* ``format``: ``blender``, ``transforms``, ``colmap`` or ``auto`` (the default);
* for ``colmap`` only: ``model`` (the sparse model folder; default: ``path`` itself when it is
  one, else the first of ``path/sparse/0``, ``path/sparse``, ``path/colmap/sparse/0``),
  ``images`` (default: the first ``images`` folder in ``path``, its parent or its grandparent)
  and ``masks`` (a folder of masks, optional).

Relative paths are taken relative to ``base`` (default: the working folder). ``auto`` looks
into the folder in this order: a ``transforms.json`` (as nerfstudio, which may also keep its
COLMAP model beside it), a ``transforms_<split>.json``, a COLMAP model.

What :func:`load_views` does to each frame, in order:

(:func:`view_intrinsics` gives the resulting intrinsics and size without decoding anything.)

1. lens distortion is removed once, into ``cache`` (:mod:`.undistort`);
2. the image is decoded to linear straight colour and the mask (a separate file, else the
   image's alpha) to coverage in [0, 1] (:mod:`.images`);
3. pixels are made square: fx and fy within 0.5 % of each other are both replaced by their
   mean; beyond that, the axis with the larger focal length (the finer pixel pitch) is shrunk by
   area resampling so that both pitches match (fy, cy, height or fx, cx, width scaled by the
   size ratio), and the difference left by rounding the size to whole pixels (under half a
   pixel across the image) is averaged away in the same way. Shrinking, never enlarging, keeps
   every output pixel an average of measured ones;
4. ``downsample`` (an integer factor): area averaging over factor×factor blocks after cropping
   the right and bottom edges to a multiple of the factor; fx, fy, cx, cy are divided by it.

Resampling (3, 4) averages premultiplied colour when the mask is the image's own alpha (so the
colour of transparent pixels does not bleed into the edges), and plain colour when the mask is a
separate file (a photograph's background is real).
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Mapping, NamedTuple

import numpy as np

from .blender import is_blender, is_split_file, read_blender
from .colmap import is_model, read_colmap
from .frames import DatasetError, Frame
from .images import downsample as area_downsample
from .images import read_image, read_mask, resize_area
from .transforms import FILE_NAME, read_transforms
from .undistort import pinhole_intrinsics, undistort_frame

FORMATS = ("blender", "transforms", "colmap", "auto")
SPEC_KEYS = ("path", "format", "model", "images", "masks")
COLMAP_KEYS = ("model", "images", "masks")

#: Relative difference of fx and fy below which their mean is used without resampling.
SQUARE_TOLERANCE = 0.005


@dataclass(eq=False)
class View:
    """A decoded photograph and its pinhole camera: ``image`` (H, W, 3) float64 linear straight
    colour, ``mask`` (H, W) float64 coverage in [0, 1] or None, ``cam_to_world`` 4×4 in OpenCV
    axes, intrinsics in pixels with the pixel-corner origin (fx = fy: square pixels), after
    undistortion and downsampling."""
    name: str
    image: np.ndarray
    mask: np.ndarray | None
    cam_to_world: np.ndarray
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    split: str
    source: Path | None = None


class Splits(NamedTuple):
    """The views (or frames) to fit, and those held out to evaluate on."""
    train: list
    held_out: list


def spec_mapping(spec) -> Mapping | None:
    """``spec`` as a mapping: a path → {'path': ...}; an object with a ``path`` attribute → its
    attributes named in :data:`SPEC_KEYS` that are not None; a mapping as it is; else None."""
    if isinstance(spec, (str, Path)):
        return {"path": spec}
    if isinstance(spec, Mapping):
        return spec
    if hasattr(spec, "path"):
        return {k: getattr(spec, k) for k in SPEC_KEYS if getattr(spec, k, None) is not None}
    return None


def normalise_spec(spec, base, where: str) -> dict:
    """``spec`` as a dict with absolute paths and a format, its keys checked."""
    spec = spec_mapping(spec)
    if spec is None:
        raise DatasetError(where, "", "expected a dataset path or a mapping with path and format")
    unknown = [k for k in spec if k not in SPEC_KEYS]
    if unknown:
        raise DatasetError(where, str(unknown[0]), f"unknown key (expected {', '.join(SPEC_KEYS)})")
    out = dict(spec)
    out.setdefault("format", "auto")
    if out["format"] not in FORMATS:
        raise DatasetError(where, "format", f"{out['format']!r} is not a format (expected {', '.join(FORMATS)})")
    for key in ("path", "model", "images", "masks"):
        if out.get(key) is not None:
            if not isinstance(out[key], (str, Path)):
                raise DatasetError(where, key, f"expected a path, got {out[key]!r}")
            out[key] = Path(base or ".") / Path(out[key]).expanduser()
    if out.get("path") is None and not (out["format"] == "colmap" and out.get("model") and out.get("images")):
        raise DatasetError(where, "path", "missing (expected the dataset folder)")
    return out


def detect_format(path: Path, where: str) -> str:
    """The format of the dataset at ``path`` (see the module docstring)."""
    if path.is_file():
        return "blender" if is_split_file(path) else "transforms"
    if not path.is_dir():
        raise DatasetError(path, "", f"not found (expected the dataset folder of {where})")
    if (path / FILE_NAME).is_file():
        return "transforms"
    if is_blender(path):
        return "blender"
    if colmap_model(path) is not None:
        return "colmap"
    raise DatasetError(path, "", f"cannot tell the dataset format (expected {FILE_NAME}, transforms_train.json "
                                 f"or a COLMAP model in sparse/0)")


def colmap_model(folder: Path) -> Path | None:
    """The COLMAP model folder of a dataset folder (see the module docstring), else None."""
    for candidate in (folder, folder / "sparse" / "0", folder / "sparse", folder / "colmap" / "sparse" / "0"):
        if is_model(candidate):
            return candidate
    return None


def colmap_images(folder: Path) -> Path:
    """The first existing ``images`` folder in ``folder``, its parent or its grandparent
    (default: ``folder/images``, reported missing by the reader)."""
    for candidate in (folder / "images", folder.parent / "images", folder.parent.parent / "images"):
        if candidate.is_dir():
            return candidate
    return folder / "images"


def read_frames(spec, *, base=None, where: str = "dataset") -> list[Frame]:
    """The frames of the dataset described by ``spec`` (a path or a mapping, see the module
    docstring), with relative paths taken from ``base``; ``where`` names the spec in messages
    (e.g. 'scene.yaml: optimize.dataset')."""
    where = str(getattr(spec, "key", None) or where)
    spec = normalise_spec(spec, base, where)
    fmt = spec["format"]
    if fmt == "auto":
        fmt = detect_format(spec["path"], where)
    extra = [k for k in COLMAP_KEYS if spec.get(k) is not None]
    if fmt != "colmap" and extra:
        raise DatasetError(where, extra[0], f"only for format colmap (this dataset is {fmt})")
    if fmt == "blender":
        return read_blender(spec["path"])
    if fmt == "transforms":
        return read_transforms(spec["path"])
    folder = spec.get("path") or spec["model"]
    model = spec.get("model") or colmap_model(folder)
    if model is None:
        raise DatasetError(folder, "", "no COLMAP model (expected cameras and images files in the folder, "
                                       "sparse/0, sparse or colmap/sparse/0)")
    images = spec.get("images") or colmap_images(folder)
    return read_colmap(model, images, spec.get("masks") or colmap_masks(folder, images))


def colmap_masks(folder: Path, images: Path) -> Path | None:
    """The ``masks`` folder of a COLMAP dataset, if there is one (masks are used whenever they are
    there): ``folder/masks``, else beside the image folder (``images/../masks``)."""
    for candidate in (Path(folder) / "masks", Path(images).parent / "masks"):
        if candidate.is_dir():
            return candidate
    return None


def check_image_size(array: np.ndarray, frame: Frame, path: Path, what: str):
    """A :class:`DatasetError` naming ``path`` when ``array`` is not the frame's size."""
    if array.shape[:2] != (frame.height, frame.width):
        raise DatasetError(path, frame.where, f"{what} is {array.shape[1]}×{array.shape[0]}, expected "
                                              f"{frame.width}×{frame.height} (the size of its image and camera)")


def square_geometry(fx, fy, cx, cy, width, height) -> tuple:
    """(f, f, cx, cy, width, height) with square pixels, by step 3 of the module docstring."""
    if abs(fx - fy) > SQUARE_TOLERANCE * 0.5 * (fx + fy):
        if fy > fx:
            new_w, new_h = width, max(1, round(height * fx / fy))
        else:
            new_w, new_h = max(1, round(width * fy / fx)), height
        sx, sy = new_w / width, new_h / height
        fx, fy, cx, cy, width, height = fx * sx, fy * sy, cx * sx, cy * sy, new_w, new_h
    f = 0.5 * (fx + fy)
    return f, f, cx, cy, width, height


def downsampled_geometry(geometry: tuple, factor: int) -> tuple:
    """(fx, fy, cx, cy, width, height) after area averaging by ``factor`` (step 4 of the module
    docstring): the intrinsics divided by it, the size by it rounded down."""
    fx, fy, cx, cy, width, height = geometry
    return fx / factor, fy / factor, cx / factor, cy / factor, width // factor, height // factor


def view_intrinsics(frame: Frame, *, downsample: int = 1, key: str = "downsample") -> tuple:
    """(fx, fy, cx, cy, width, height) of the view :func:`load_views` makes of ``frame``,
    computed from the frame alone (no image is decoded): undistortion, square pixels and
    downsampling change them. ``key`` names ``downsample`` in messages."""
    fx, fy, cx, cy = pinhole_intrinsics(frame) if frame.distortion else (frame.fx, frame.fy, frame.cx, frame.cy)
    factor = check_factor(downsample, [frame], key)
    return downsampled_geometry(square_geometry(fx, fy, cx, cy, frame.width, frame.height), factor)


def check_factor(factor, frames: list[Frame], key: str = "downsample") -> int:
    """``factor`` as an int ≥ 1 no larger than the smallest image side, else a PsdrError naming
    ``key`` (e.g. 'exp.yaml: optimize.target.dataset.downsample')."""
    ok = isinstance(factor, (int, np.integer)) and not isinstance(factor, bool) and factor >= 1
    smallest = min(min(f.width, f.height) for f in frames) if frames else 1
    if not ok or factor > smallest:
        raise DatasetError(key, "", f"{factor!r} is not usable (expected an integer from 1 to {smallest}, "
                                    f"the smallest image side)")
    return int(factor)


def load_view(frame: Frame, factor: int, linear: bool, cache) -> View:
    """One frame decoded, undistorted, made square-pixelled and downsampled (module docstring)."""
    if frame.distortion:
        if cache is None:
            raise DatasetError(frame.source or frame.image, frame.where,
                               "has lens distortion, so load_views needs a cache folder (expected cache=...)")
        frame = undistort_frame(frame, cache, linear=linear)
    rgb, alpha = read_image(frame.image, linear=linear, where=frame.where)
    check_image_size(rgb, frame, frame.image, "image")
    if frame.mask is not None:
        mask = read_mask(frame.mask, where=frame.where)
        check_image_size(mask, frame, frame.mask, "mask")
        premultiplied = False
    else:
        mask, premultiplied = alpha, alpha is not None
    colour = rgb * mask[..., None] if premultiplied else rgb
    square = square_geometry(frame.fx, frame.fy, frame.cx, frame.cy, frame.width, frame.height)
    if square[4:] != (frame.width, frame.height):
        colour = resize_area(colour, *square[4:])
        mask = None if mask is None else resize_area(mask, *square[4:])
    if factor > 1:
        colour = area_downsample(colour, factor)
        mask = None if mask is None else area_downsample(mask, factor)
    fx, fy, cx, cy, width, height = downsampled_geometry(square, factor)
    if premultiplied:
        colour = np.where(mask[..., None] > 0, colour / np.where(mask > 0, mask, 1.0)[..., None], 0.0)
    return View(name=frame.name, image=np.ascontiguousarray(colour), mask=mask,
                cam_to_world=np.array(frame.cam_to_world, np.float64), fx=float(fx), fy=float(fy),
                cx=float(cx), cy=float(cy), width=int(width), height=int(height), split=frame.split,
                source=frame.source)


def load_views(frames: list[Frame], *, downsample: int = 1, linear: bool = False, cache=None,
               key: str = "downsample") -> list[View]:
    """The :class:`View` of every frame (module docstring). ``linear``: the 8/16-bit images are
    already linear (no sRGB decoding). ``cache``: the folder for undistorted images (needed only
    when a frame has lens distortion)."""
    factor = check_factor(downsample, frames, key)
    return [load_view(frame, factor, linear, cache) for frame in frames]


def split_views(views: list, holdout_every: int | None = None, key: str | None = None) -> Splits:
    """(train, held_out) of ``views`` (:class:`View` or :class:`Frame` records, in dataset
    order). With ``holdout_every`` None, the dataset's own splits: its 'train' records, and its
    'test' records, else (a dataset without a test split) its 'val' records. With
    ``holdout_every`` = k, every k-th record counting from the first (index i with i mod k = 0,
    as mip-NeRF 360 holds out its test views) is held out as 'test' and the others are 'train',
    the dataset's own splits ignored. An empty training split, or a k outside 2..len(views), is a
    :class:`DatasetError` (naming ``key``, e.g. 'exp.yaml: optimize.target.dataset.holdout_every',
    else the dataset); the held-out list may be empty (a dataset without val or test)."""
    where = next((v.source for v in views if getattr(v, "source", None) is not None), "dataset")
    if not views:
        raise DatasetError(where, "", "no views (expected at least one frame)")
    if holdout_every is None:
        train = [v for v in views if v.split == "train"]
        held_out = [v for v in views if v.split == "test"] or [v for v in views if v.split == "val"]
    else:
        k = holdout_every
        if not isinstance(k, (int, np.integer)) or isinstance(k, bool) or not 2 <= k <= len(views):
            raise DatasetError(key or where, "" if key else "holdout_every",
                               f"{k!r} is not usable (expected an integer from 2 to {len(views)}, the number of views)")
        train = [replace(v, split="train") for i, v in enumerate(views) if i % k]
        held_out = [replace(v, split="test") for i, v in enumerate(views) if i % k == 0]
    if not train:
        raise DatasetError(where, "split train", "empty (expected at least one training view)")
    return Splits(train, held_out)
