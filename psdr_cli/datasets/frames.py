"""One photograph and its camera, whatever dataset it came from (:class:`Frame`), and the checks
every reader applies to it.

Conventions of a :class:`Frame`:

* ``cam_to_world`` maps camera coordinates to world coordinates in **OpenCV camera axes**
  (x right, y down, z forward, the camera looks along +z); it is rigid.
* Intrinsics are in pixels of the image's own resolution. The pixel coordinate origin is the
  **top-left corner of the top-left pixel**, so the centre of pixel (i, j) (column i, row j) is
  (i + 0.5, j + 0.5). A camera point (x, y, z) projects to u = fx·x/z + cx, v = fy·y/z + cy.
  This is COLMAP's convention (the centre of the upper-left pixel is (0.5, 0.5)), nerfstudio's
  (its rays go through pixel + 0.5) and instant-ngp's, and the one that makes a centred camera
  have cx = width/2. OpenCV's own functions put the origin at the centre of the top-left pixel:
  pass them cx − 0.5, cy − 0.5 (:func:`opencv_matrix`).
* ``distortion`` holds OpenCV's coefficients (k1, k2, p1, p2[, k3[, k4, k5, k6]]) or () for an
  ideal pinhole.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..config.limits import MAX_PRINCIPAL_OFFSET
from ..errors import PsdrError, PsdrWarning

SPLITS = ("train", "val", "test")

#: Tolerance of a camera matrix's last row (0, 0, 0, 1).
RIGID_TOLERANCE = 1e-4

#: Largest max |RᵀR − I| of a camera rotation that is read, as the nearest rotation (R = U·Vᵀ of
#: R's singular value decomposition): a matrix written with 4 decimals is up to ~3·10⁻⁴ off, with 3
#: decimals ~3·10⁻³; beyond this it is scaled or sheared, not rounded.
ORTHONORMAL_TOLERANCE = 5e-3

#: Right-multiplying a camera-to-world matrix in OpenGL axes (x right, y up, z backward) by this
#: flips its y and z columns and gives the same camera in OpenCV axes (x right, y down, z forward).
OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])


class DatasetError(PsdrError):
    """A bad dataset input: ``<file>: <frame or key>: <what was expected>``, on one line."""

    def __init__(self, file, where: str, message: str):
        self.file, self.where, self.message = str(file), where, message
        super().__init__(f"{self.file}: {where}: {message}" if where else f"{self.file}: {message}")


class MissingImage(DatasetError):
    """A frame whose image file does not exist (readers skip such frames: :func:`frames_with_images`)."""


def frames_with_images(file, makers) -> list:
    """The frame each of ``makers`` (callables) makes, skipping those whose image is missing, as
    instant-ngp and nerfstudio do: one warning counts them and names the first; a dataset with
    no image left is one :class:`DatasetError`."""
    frames, missing = [], []
    for make in makers:
        try:
            frames.append(make())
        except MissingImage as exc:
            missing.append(exc)
    if missing and not frames:
        raise DatasetError(file, "", f"none of its {len(missing)} frames has its image (the first: {missing[0].where}: "
                                     f"{missing[0].message})")
    if missing:
        warnings.warn(f"{file}: {len(missing)} of {len(missing) + len(frames)} frames skipped, their image is missing "
                      f"(the first: {missing[0].where}: {missing[0].message})", PsdrWarning, stacklevel=3)
    return frames


@dataclass(frozen=True, eq=False)
class Frame:
    """A photograph (``image``, optional separate ``mask``: None = the image's alpha, if any) and
    its camera, in the conventions of this module's docstring. ``source`` is the file or folder
    the camera was read from (for messages); ``has_alpha``: the image has an alpha channel (by
    its header), so that a frame with ``mask`` None still has a mask. ``cam_to_world`` is stored as a read-only float64
    copy; frames compare by identity (they hold an array)."""
    name: str
    image: Path
    mask: Path | None
    cam_to_world: np.ndarray
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    distortion: tuple = ()
    split: str = "train"
    source: Path | None = None
    has_alpha: bool = False

    def __post_init__(self):
        matrix = np.array(self.cam_to_world, dtype=np.float64)
        matrix.setflags(write=False)
        if matrix.shape != (4, 4):
            raise ValueError(f"Frame {self.name}: cam_to_world must be 4×4, not {matrix.shape}")
        if len(self.distortion) not in (0, 4, 5, 8):
            raise ValueError(f"Frame {self.name}: distortion must have 0, 4, 5 or 8 OpenCV coefficients")
        if self.split not in SPLITS:
            raise ValueError(f"Frame {self.name}: split must be one of {SPLITS}, not {self.split!r}")
        object.__setattr__(self, "cam_to_world", matrix)
        object.__setattr__(self, "image", Path(self.image))
        object.__setattr__(self, "mask", None if self.mask is None else Path(self.mask))
        object.__setattr__(self, "distortion", tuple(float(c) for c in self.distortion))

    @property
    def where(self) -> str:
        """'frame <name>' for messages."""
        return f"frame {self.name}"


def opencv_matrix(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """The 3×3 camera matrix for OpenCV functions, whose pixel origin is the centre of the
    top-left pixel: [[fx, 0, cx − ½], [0, fy, cy − ½], [0, 0, 1]]."""
    return np.array([[fx, 0.0, cx - 0.5], [0.0, fy, cy - 0.5], [0.0, 0.0, 1.0]])


def opengl_to_opencv(cam_to_world: np.ndarray) -> np.ndarray:
    """The same camera-to-world matrix with OpenCV camera axes: C · diag(1, −1, −1, 1)."""
    return np.asarray(cam_to_world, np.float64) @ OPENGL_TO_OPENCV


def focal_from_fov(size: float, fov: float) -> float:
    """Focal length in pixels of a full field of view ``fov`` (radians) across ``size`` pixels:
    f = (size / 2) / tan(fov / 2)."""
    return 0.5 * size / np.tan(0.5 * fov)


def principal_coordinate(value: float, size: int, file, key: str) -> float:
    """``value`` (cx across ``size`` = the width, or cy across the height, in pixels) when the
    principal point lies within :data:`~psdr_cli.config.limits.MAX_PRINCIPAL_OFFSET` image sizes of
    the image's centre, as psdr's cameras need, else a :class:`DatasetError` naming ``key``."""
    low, high = size * (0.5 - MAX_PRINCIPAL_OFFSET), size * (0.5 + MAX_PRINCIPAL_OFFSET)
    if not low <= value <= high:
        raise DatasetError(file, key, f"{value:g}: expected a principal point coordinate from {low:g} to {high:g} "
                                      f"(within {MAX_PRINCIPAL_OFFSET:g} image size of the centre of the {size}-pixel side)")
    return value


def rigid_matrix(value, file, where: str) -> np.ndarray:
    """``value`` as a 4×4 float64 camera-to-world matrix, or a :class:`DatasetError`: it must be
    finite, its last row (0, 0, 0, 1), its rotation R a rotation (det R > 0) up to rounding (max
    |RᵀR − I| ≤ :data:`ORTHONORMAL_TOLERANCE`), which is replaced by the nearest rotation."""
    expected = "expected a rigid 4×4 camera-to-world matrix (finite, RᵀR = I, det R = +1, last row 0 0 0 1)"
    try:
        m = np.array(value, dtype=np.float64)  # (a copy: the rotation is replaced in place)
    except (TypeError, ValueError):
        raise DatasetError(file, where, expected) from None
    if m.shape == (3, 4):
        m = np.vstack([m, [0.0, 0.0, 0.0, 1.0]])
    if m.shape != (4, 4):
        raise DatasetError(file, where, f"{expected}; got shape {m.shape}")
    if not np.all(np.isfinite(m)):
        raise DatasetError(file, where, f"{expected}; it has NaN or infinite entries")
    if np.max(np.abs(m[3] - [0.0, 0.0, 0.0, 1.0])) > RIGID_TOLERANCE:
        raise DatasetError(file, where, f"{expected}; its last row is {m[3].tolist()}")
    r = m[:3, :3]
    det = float(np.linalg.det(r))
    if det <= 0.0:
        raise DatasetError(file, where, f"{expected}; det R = {det:.4g} (a reflection)")
    off = float(np.max(np.abs(r.T @ r - np.eye(3))))
    if off > ORTHONORMAL_TOLERANCE:
        raise DatasetError(file, where, f"{expected}; RᵀR differs from I by {off:.2g} (scaled or sheared, "
                                        f"beyond the {ORTHONORMAL_TOLERANCE:g} of a rounded matrix)")
    u, _, vt = np.linalg.svd(r)
    m[:3, :3] = u @ vt
    return m


def check_same_size(frames: list[Frame]) -> list[Frame]:
    """``frames`` unchanged when all images have the first one's size, else a
    :class:`DatasetError` naming the first frame that differs."""
    if not frames:
        return frames
    first = frames[0]
    for f in frames[1:]:
        if (f.width, f.height) != (first.width, first.height):
            raise DatasetError(f.source or f.image, f.where,
                               f"image {f.image} is {f.width}×{f.height}, expected {first.width}×{first.height} "
                               f"like frame {first.name} (one size per dataset)")
    return frames


def distortion_tuple(k1=0.0, k2=0.0, p1=0.0, p2=0.0, k3=0.0) -> tuple:
    """OpenCV's coefficient tuple: () when all are zero, (k1, k2, p1, p2) when k3 is zero, else
    (k1, k2, p1, p2, k3)."""
    coeffs = tuple(float(c) for c in (k1, k2, p1, p2, k3))
    if not any(coeffs):
        return ()
    return coeffs if coeffs[4] else coeffs[:4]
