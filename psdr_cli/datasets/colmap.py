"""COLMAP sparse models (``cameras``, ``images`` and ``points3D``, binary ``.bin`` or text
``.txt``, in a model folder such as ``sparse/0``), read with pycolmap.

COLMAP stores world-to-camera poses (``cam_from_world``) in OpenCV camera axes (x right, y down,
z forward); a frame's ``cam_to_world`` is its inverse. Its pixel origin is the corner of the
top-left pixel (the centre of that pixel is (0.5, 0.5)), as in :mod:`.frames`.

Camera models and their parameters, with the OpenCV distortion tuple they become:

=============== ============================== ==========================
SIMPLE_PINHOLE  f, cx, cy                      ()
PINHOLE         fx, fy, cx, cy                 ()
SIMPLE_RADIAL   f, cx, cy, k                   (k, 0, 0, 0)
RADIAL          f, cx, cy, k1, k2              (k1, k2, 0, 0)
OPENCV          fx, fy, cx, cy, k1, k2, p1, p2 (k1, k2, p1, p2)
=============== ============================== ==========================

(all-zero coefficients become ()). Any other model is refused. Images are those of the model
with a pose, sorted by name, found as ``<images>/<name>`` (a missing file is refused; files in
the folder that the model does not register are ignored). A mask folder, when given, must hold
a mask for every image: ``<masks>/<name>.png`` (COLMAP's own convention, e.g. ``a.jpg.png``),
else ``<masks>/<name with its extension replaced by .png>`` (e.g. ``a.png``), tried in this
order. A model without ``points3D`` is read as if it had no points.
"""
from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

import numpy as np

from .frames import DatasetError, Frame, check_same_size, distortion_tuple, rigid_matrix
from .images import has_alpha, image_dimensions

#: Parameter names of the supported models, in COLMAP's order.
MODELS = {
    "SIMPLE_PINHOLE": ("f", "cx", "cy"),
    "PINHOLE": ("fx", "fy", "cx", "cy"),
    "SIMPLE_RADIAL": ("f", "cx", "cy", "k1"),
    "RADIAL": ("f", "cx", "cy", "k1", "k2"),
    "OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"),
}

MODEL_FILES = ("rigs", "cameras", "frames", "images", "points3D")


def model_format(model: Path) -> str | None:
    """'bin' or 'txt' by which cameras and images files ``model`` holds (binary first, as COLMAP
    reads them), else None."""
    for ext in ("bin", "txt"):
        if (model / f"cameras.{ext}").is_file() and (model / f"images.{ext}").is_file():
            return ext
    return None


def is_model(folder: Path) -> bool:
    """Whether ``folder`` is a COLMAP model folder."""
    return Path(folder).is_dir() and model_format(Path(folder)) is not None


def read_reconstruction(model: Path):
    """The pycolmap reconstruction of ``model``; a model without points3D is completed with an
    empty one in a temporary copy. Unreadable files are a :class:`DatasetError`. pycolmap is
    imported here, for the COLMAP datasets only (it adds a third of a second to every start)."""
    import pycolmap
    ext = model_format(model)
    if ext is None:
        raise DatasetError(model, "", "no cameras.bin and images.bin, nor cameras.txt and images.txt "
                                      "(expected a COLMAP sparse model folder such as sparse/0)")
    try:
        if (model / f"points3D.{ext}").is_file():
            return pycolmap.Reconstruction(str(model))
        with tempfile.TemporaryDirectory(prefix="psdr-colmap-") as tmp:
            for name in MODEL_FILES:
                if (model / f"{name}.{ext}").is_file():
                    shutil.copyfile(model / f"{name}.{ext}", Path(tmp) / f"{name}.{ext}")
            (Path(tmp) / f"points3D.{ext}").write_bytes(bytes(8) if ext == "bin" else b"")  # no points
            return pycolmap.Reconstruction(tmp)
    except (ValueError, RuntimeError, OSError) as exc:
        detail = str(exc).strip().splitlines()[-1] if str(exc).strip() else type(exc).__name__
        raise DatasetError(model / f"images.{ext}", "", f"not a readable COLMAP model ({detail[:160]})") from None


def cam_from_world(image) -> np.ndarray:
    """The 3×4 world-to-camera matrix of a pycolmap image (a property in older pycolmap, a
    method in newer ones)."""
    pose = image.cam_from_world
    pose = pose() if callable(pose) else pose
    return np.asarray(pose.matrix(), np.float64)


def camera_intrinsics(camera, file: Path, camera_id: int) -> tuple:
    """(fx, fy, cx, cy, distortion) of a pycolmap camera, by the table in the module docstring."""
    model = camera.model.name if hasattr(camera.model, "name") else str(camera.model)
    if model not in MODELS:
        raise DatasetError(file, f"camera {camera_id}", f"model {model} is not supported "
                                                        f"(expected one of {', '.join(MODELS)})")
    p = dict(zip(MODELS[model], (float(v) for v in camera.params)))
    fx, fy = p.get("fx", p.get("f")), p.get("fy", p.get("f"))
    dist = distortion_tuple(p.get("k1", 0.0), p.get("k2", 0.0), p.get("p1", 0.0), p.get("p2", 0.0))
    return fx, fy, p["cx"], p["cy"], dist


def mask_file(masks: Path, name: str) -> Path | None:
    """``<masks>/<name>.png``, else ``<masks>/<name with suffix .png>``, whichever exists first."""
    for candidate in (masks / f"{name}.png", (masks / name).with_suffix(".png")):
        if candidate.is_file():
            return candidate
    return None


def read_colmap(model, images, masks=None) -> list[Frame]:
    """The frames of a COLMAP model folder, with images from ``images`` and masks, if given,
    from ``masks`` (see the module docstring)."""
    model, images = Path(model), Path(images)
    if not model.is_dir():
        raise DatasetError(model, "", "not a folder (expected a COLMAP sparse model folder such as sparse/0)")
    rec = read_reconstruction(model)
    ext = model_format(model)
    cameras_file, images_file = model / f"cameras.{ext}", model / f"images.{ext}"
    posed = sorted((im for im in rec.images.values() if image_has_pose(im)), key=lambda im: im.name)
    if not posed:
        raise DatasetError(images_file, "", "no registered images (expected a model with posed images)")
    if not images.is_dir():
        raise DatasetError(images, "", f"not a folder (expected the images of {images_file})")
    if masks is not None and not Path(masks).is_dir():
        raise DatasetError(masks, "", "not a folder (expected a folder of mask files)")
    frames = []
    for im in posed:
        where = f"image {im.image_id} ({im.name})"
        camera = rec.cameras[im.camera_id]
        fx, fy, cx, cy, dist = camera_intrinsics(camera, cameras_file, im.camera_id)
        path = images / im.name
        width, height = image_dimensions(path, images_file, where)
        if (width, height) != (camera.width, camera.height):
            raise DatasetError(images_file, where, f"image {path} is {width}×{height}, expected "
                                                   f"{camera.width}×{camera.height} like camera {im.camera_id}")
        mask = None
        if masks is not None:
            mask = mask_file(Path(masks), im.name)
            if mask is None:
                raise DatasetError(masks, where, f"no mask {im.name}.png or {Path(im.name).with_suffix('.png')} "
                                                 f"(expected a mask for every image)")
        w2c = rigid_matrix(cam_from_world(im), images_file, f"{where} pose")
        frames.append(Frame(name=im.name, image=path, mask=mask, cam_to_world=np.linalg.inv(w2c),
                            fx=fx, fy=fy, cx=cx, cy=cy, width=width, height=height, distortion=dist,
                            split="train", source=images_file, has_alpha=has_alpha(path)))
    return check_same_size(frames)


def image_has_pose(image) -> bool:
    """Whether a pycolmap image is registered (``has_pose``; older pycolmap: ``registered``)."""
    flag = getattr(image, "has_pose", None)
    if flag is None:
        flag = getattr(image, "registered", True)
    return bool(flag() if callable(flag) else flag)
