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

(all-zero coefficients become ()). Any other model is refused, and so is a focal length below one
pixel or a principal point that is not a finite number. Images are those of the model
with a pose, sorted by name, found as ``<images>/<name>`` (a missing file is refused; files in
the folder that the model does not register are ignored). A mask folder, when given, must hold
a mask for every image: ``<masks>/<name>.png`` (COLMAP's own convention, e.g. ``a.jpg.png``),
else ``<masks>/<name with its extension replaced by .png>`` (e.g. ``a.png``), tried in this
order. A model without ``points3D`` is read as if it had no points.

Poses are read as COLMAP reads them: a quaternion of any nonzero length is normalised (one warning
when some are more than :data:`QUATERNION_TOLERANCE` from length 1, e.g. written with 4 decimals
or scaled); a zero or non-finite quaternion is refused. Two images of one name are refused, and
so is an ``images.txt`` image whose second line (its 2D points, possibly empty) is missing: COLMAP
would read the next image's pose line as those points, or meet the end of the file, and drop an
image without a word. A folder with both forms is read in the binary one, as COLMAP does, with a
warning when the text form disagrees with it.
"""
from __future__ import annotations

import math
import re
import shutil
import tempfile
import warnings
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from ..errors import PsdrWarning
from .frames import (DatasetError, Frame, check_same_size, distortion_tuple, frames_with_images, principal_coordinate,
                     rigid_matrix)
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

#: pycolmap's messages about the cameras file ("Check failed: line_stream >> camera.camera_id ...",
#: "camera.VerifyParams()", "Camera model does not exist"); any other names the images file.
CAMERA_FILE_ERROR = re.compile(r"\bcamera\.|camera model", re.IGNORECASE)

#: How far from 1 a pose quaternion's length may be before its normalisation is reported.
QUATERNION_TOLERANCE = 1e-3


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


def read_reconstruction(model: Path, ext: str | None = None, points: bool = True):
    """The pycolmap reconstruction of ``model`` in its ``ext`` form ('bin' or 'txt'; default: the
    one COLMAP reads, :func:`model_format`); a model without points3D, or read without them
    (``points`` false), is completed with an empty one in a temporary copy. Unreadable files are a :class:`DatasetError`. pycolmap is imported
    here, for the COLMAP datasets only (it adds a third of a second to every start)."""
    import pycolmap
    first = model_format(model)
    if first is None:
        raise DatasetError(model, "", "no cameras.bin and images.bin, nor cameras.txt and images.txt "
                                      "(expected a COLMAP sparse model folder such as sparse/0)")
    ext = ext or first
    try:
        has_points = points and (model / f"points3D.{ext}").is_file()
        if ext == first and has_points:
            return pycolmap.Reconstruction(str(model))
        with tempfile.TemporaryDirectory(prefix="psdr-colmap-") as tmp:
            for name in MODEL_FILES:
                if (model / f"{name}.{ext}").is_file() and (name != "points3D" or has_points):
                    shutil.copyfile(model / f"{name}.{ext}", Path(tmp) / f"{name}.{ext}")
            if not has_points:
                (Path(tmp) / f"points3D.{ext}").write_bytes(bytes(8) if ext == "bin" else b"")  # no points
            return pycolmap.Reconstruction(tmp)
    except Exception as exc:  # noqa: BLE001 - pycolmap raises IndexError, KeyError, ... for bad models
        detail = str(exc).strip().splitlines()[-1] if str(exc).strip() else type(exc).__name__
        file = model / f"{'cameras' if CAMERA_FILE_ERROR.search(detail) else 'images'}.{ext}"
        raise DatasetError(file, "", f"not a readable COLMAP model ({detail[:160]})") from None


def forms_disagreement(binary, text) -> str | None:
    """How the binary and text forms of one model (pycolmap reconstructions) disagree: images in
    one form only, a pose or a camera's parameters more than 10⁻⁶ (relative) apart; None when
    they agree."""
    a = {im.name: im for im in binary.images.values()}
    b = {im.name: im for im in text.images.values()}
    if set(a) != set(b):
        return f"images {', '.join(sorted(set(a) ^ set(b))[:3])} are in one form only"
    for name in sorted(a):
        pa, pb = (np.asarray((p() if callable(p) else p).matrix()) for p in (a[name].cam_from_world, b[name].cam_from_world))
        if np.abs(pa - pb).max() > 1e-6 * (1.0 + np.abs(pa).max()):
            return f"the pose of image {name} differs by {np.abs(pa - pb).max():.3g}"
        ca, cb = binary.cameras[a[name].camera_id], text.cameras[b[name].camera_id]
        if not np.allclose(np.asarray(ca.params), np.asarray(cb.params), rtol=1e-6, atol=1e-9):
            return f"the parameters of image {name}'s camera differ"
    return None


def warn_if_forms_disagree(model: Path, rec):
    """One warning when ``model`` holds both forms and they disagree (COLMAP reads the binary one)."""
    if model_format(model) != "bin" or not all((model / f"{n}.txt").is_file() for n in ("cameras", "images")):
        return
    try:
        text = read_reconstruction(model, "txt", points=False)
    except DatasetError as exc:
        text, why = None, f"the text form is not readable ({exc.message})"
    else:
        why = forms_disagreement(rec, text)
    if why:
        warnings.warn(f"{model}: cameras.bin/images.bin and cameras.txt/images.txt disagree ({why}); reading the "
                      f"binary files, as COLMAP does", PsdrWarning, stacklevel=3)


def cam_from_world(image, file: Path, where: str) -> tuple:
    """(the 4×4 world-to-camera matrix of a pycolmap image with its quaternion normalised, the
    quaternion's length as read). A zero or non-finite quaternion is a :class:`DatasetError`."""
    pose = image.cam_from_world
    pose = pose() if callable(pose) else pose  # (a property in older pycolmap, a method in newer ones)
    q = np.asarray(pose.rotation.quat, np.float64)  # x, y, z, w as read from the file
    length = float(np.linalg.norm(q))
    if not np.isfinite(q).all() or length < 1e-6:
        w, x, y, z = q[3], q[0], q[1], q[2]
        raise DatasetError(file, f"{where} quaternion", f"QW QX QY QZ = {w:g} {x:g} {y:g} {z:g}: expected a "
                                                        f"rotation (a nonzero quaternion; COLMAP normalises it)")
    w2c = np.eye(4)
    w2c[:3, :3] = Rotation.from_quat(q / length).as_matrix()
    w2c[:3, 3] = np.asarray(pose.translation, np.float64)
    return w2c, length


def warn_unnormalised(file: Path, lengths: dict):
    """One warning when some quaternions' lengths (image name → length) are more than
    :data:`QUATERNION_TOLERANCE` from 1."""
    off = {name: n for name, n in lengths.items() if abs(n - 1.0) > QUATERNION_TOLERANCE}
    if off:
        name, n = max(off.items(), key=lambda item: abs(item[1] - 1.0))
        warnings.warn(f"{file}: {len(off)} pose quaternion(s) not of length 1 (the farthest: {name}, "
                      f"{n:.6g}); normalised, as COLMAP does", PsdrWarning, stacklevel=3)


def check_points_lines(file: Path):
    """Refuses an ``images.txt`` in which an image's pose line is not followed by its line of 2D
    points (``x y point3D_id`` triples or an empty line), read as COLMAP reads the file: the pose
    line is the next line that is neither empty nor a comment, the points line the one after it."""
    lines = file.read_text(encoding="utf-8", errors="replace").splitlines()
    i = 0
    while i < len(lines):
        line = lines[i].strip()
        i += 1
        if not line or line.startswith("#"):
            continue
        if i >= len(lines) or not is_points_line(lines[i]):
            after = "the file ends" if i >= len(lines) else f"line {i + 1} is another pose line"
            raise DatasetError(file, f"line {i}", f"image '{line.split()[0]}' has no line of 2D points ({after}; "
                                                  f"expected two lines per image, the second empty when there are "
                                                  f"no points: COLMAP would drop the image)")
        i += 1


def is_points_line(line: str) -> bool:
    """Whether ``line`` can be an images.txt line of 2D points: empty, or numbers in triples."""
    tokens = line.split()
    if len(tokens) % 3:
        return False
    try:
        [float(t) for t in tokens]
    except ValueError:
        return False
    return True


def check_unique_names(images, file: Path):
    """Refuses two registered images of one name (two poses for one photograph)."""
    first = {}
    for im in sorted(images, key=lambda im: im.image_id):
        if im.name in first:
            raise DatasetError(file, f"image {im.image_id} ({im.name})", f"the name of image {first[im.name]} too "
                                                                         f"(expected one pose per photograph)")
        first[im.name] = im.image_id


def camera_intrinsics(camera, file: Path, camera_id: int) -> tuple:
    """(fx, fy, cx, cy, distortion) of a pycolmap camera, by the table in the module docstring."""
    model = camera.model.name if hasattr(camera.model, "name") else str(camera.model)
    if model not in MODELS:
        raise DatasetError(file, f"camera {camera_id}", f"model {model} is not supported "
                                                        f"(expected one of {', '.join(MODELS)})")
    p = dict(zip(MODELS[model], (float(v) for v in camera.params)))
    for key, value in p.items():
        if not math.isfinite(value) or (key in ("f", "fx", "fy") and value < 1.0):
            raise DatasetError(file, f"camera {camera_id} {key}", f"{value:g}: expected "
                                                                  f"{'a focal length of at least 1 px' if key[0] == 'f' else 'a finite number'}")
    fx, fy = p.get("fx", p.get("f")), p.get("fy", p.get("f"))
    principal_coordinate(p["cx"], camera.width, file, f"camera {camera_id} cx")
    principal_coordinate(p["cy"], camera.height, file, f"camera {camera_id} cy")
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
    warn_if_forms_disagree(model, rec)
    ext = model_format(model)
    cameras_file, images_file = model / f"cameras.{ext}", model / f"images.{ext}"
    if ext == "txt":
        check_points_lines(images_file)
    posed = sorted((im for im in rec.images.values() if image_has_pose(im)), key=lambda im: im.name)
    if not posed:
        raise DatasetError(images_file, "", "no registered images (expected a model with posed images)")
    check_unique_names(posed, images_file)
    lengths = {}
    if not images.is_dir():
        raise DatasetError(images, "", f"not a folder (expected the images of {images_file})")
    if masks is not None and not Path(masks).is_dir():
        raise DatasetError(masks, "", "not a folder (expected a folder of mask files)")
    files = ColmapFiles(cameras_file, images_file, images, masks)
    frames = frames_with_images(images_file, [partial(colmap_frame, rec, im, files, lengths) for im in posed])
    warn_unnormalised(images_file, lengths)
    return check_same_size(frames)


@dataclass(frozen=True)
class ColmapFiles:
    """Where a COLMAP model's frames come from: its cameras and images files, the image folder and
    the mask folder (or None)."""
    cameras: Path
    images_file: Path
    images: Path
    masks: Path | None


def colmap_frame(rec, im, files: ColmapFiles, lengths: dict) -> Frame:
    """The frame of registered image ``im`` of ``rec`` (its quaternion's length into ``lengths``)."""
    where = f"image {im.image_id} ({im.name})"
    camera = rec.cameras[im.camera_id]
    fx, fy, cx, cy, dist = camera_intrinsics(camera, files.cameras, im.camera_id)
    path = files.images / im.name
    width, height = image_dimensions(path, files.images_file, where)
    if (width, height) != (camera.width, camera.height):
        raise DatasetError(files.images_file, where, f"image {path} is {width}×{height}, expected "
                                                     f"{camera.width}×{camera.height} like camera {im.camera_id}")
    mask = None
    if files.masks is not None:
        mask = mask_file(Path(files.masks), im.name)
        if mask is None:
            raise DatasetError(files.masks, where, f"no mask {im.name}.png or {Path(im.name).with_suffix('.png')} "
                                                   f"(expected a mask for every image)")
    w2c, lengths[im.name] = cam_from_world(im, files.images_file, where)
    w2c = rigid_matrix(w2c, files.images_file, f"{where} pose")
    return Frame(name=im.name, image=path, mask=mask, cam_to_world=np.linalg.inv(w2c), fx=fx, fy=fy, cx=cx, cy=cy,
                 width=width, height=height, distortion=dist, split="train", source=files.images_file,
                 has_alpha=has_alpha(path))


def image_has_pose(image) -> bool:
    """Whether a pycolmap image is registered (``has_pose``; older pycolmap: ``registered``)."""
    flag = getattr(image, "has_pose", None)
    if flag is None:
        flag = getattr(image, "registered", True)
    return bool(flag() if callable(flag) else flag)
