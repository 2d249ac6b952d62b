"""Removing lens distortion once, into a cache folder. Reads a frame's image and mask; writes
their undistorted copies there and returns the frame with its new pinhole camera.

A frame with distortion coefficients is resampled (OpenCV ``initUndistortRectifyMap`` and
``remap``, bilinear, in linear colour) into an ideal pinhole image of the **same size**. Its new
camera matrix starts from ``getOptimalNewCameraMatrix`` with alpha = 0, which zooms in until
every output pixel sees the photograph (no blank border: a blank border could not be told from
a dark object, since a frame's mask is its coverage, not a validity map). That matrix may change
the aspect of the pixels; so both focal lengths are scaled by the larger of its two zooms,
s = max(fx′/fx, fy′/fy), keeping fy/fx, and the principal point is placed so that the view stays
centred in the fully covered region:

    fx″ = s·fx,  fy″ = s·fy,  cx″ = W/2 − fx″·(x₀ + x₁)/2  (likewise cy″ with y₀, y₁),

where [x₀, x₁] is the normalised range that OpenCV's matrix gives the pixel centres.

The result is a float32 EXR (linear RGB, premultiplied by alpha when the source has alpha, the
EXR convention) and, for a separate mask file, a one-channel (Y) EXR remapped with the same map
(bilinear, clipped to [0, 1]: coverage). Both are named ``<image stem>-<hash>.exr`` and
``<image stem>-<hash>.mask.exr``, the hash (SHA-256, 16 hex digits) covering the bytes of the
image and mask files, the intrinsics, the coefficients and the ``linear`` flag; each file is
written to a temporary name and renamed into place (:func:`psdr_cli.support.fileio.write_exr`). When
both already exist they are reused as they are.

A lens model that cannot be the lens's is refused before anything is resampled: one whose radial
part r ↦ r·(1 + k1·r² + k2·r⁴ + k3·r⁶) turns back before it reaches the image's corners (the
undistortion would fold the image onto itself), and one whose undistortion would change the
image's scale by more than :data:`MAX_ZOOM` (k1 = 50 zoomed a photograph 13×).
"""
from __future__ import annotations

import hashlib
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from ..support.fileio import write_exr
from .frames import DatasetError, Frame, opencv_matrix
from .images import read_image, read_mask

#: Bumped when the cached files would come out differently.
CACHE_VERSION = 1

#: Largest change of scale (fx″/fx or fx/fx″) the undistortion of a plausible lens model makes.
MAX_ZOOM = 2.0


def corner_radius(frame: Frame) -> float:
    """The largest normalised radius |((u − cx)/fx, (v − cy)/fy)| of the image's four corners."""
    u = np.array([0.0, frame.width]) - frame.cx
    v = np.array([0.0, frame.height]) - frame.cy
    return float(np.sqrt((u[:, None] / frame.fx) ** 2 + (v[None, :] / frame.fy) ** 2).max())


def radial_turn(distortion: tuple, reach: float) -> float | None:
    """The normalised radius at which the radial model r·(1 + k1 r² + k2 r⁴ + k3 r⁶) stops growing
    before its value reaches ``reach``, or None when it grows all the way there."""
    k1, k2, _, _, k3 = (tuple(distortion) + (0.0,) * 5)[:5]
    r = np.linspace(0.0, 1.0, 20001) * max(4.0 * reach, 4.0)
    r2 = r * r
    g = r * (1.0 + k1 * r2 + k2 * r2 * r2 + k3 * r2 ** 3)
    growing = np.diff(g) > 0
    reached = np.nonzero(g >= reach)[0]
    end = reached[0] if len(reached) else len(g) - 1
    turns = np.nonzero(~growing[:end])[0]
    return float(r[turns[0]]) if len(turns) else (None if len(reached) else float(r[np.argmax(g)]))


def check_lens(frame: Frame, intrinsics: tuple):
    """Refuses a lens model that cannot be the lens's (module docstring)."""
    names = ", ".join(f"{k} = {c:g}" for k, c in zip(("k1", "k2", "p1", "p2", "k3"), frame.distortion) if c)
    turn = radial_turn(frame.distortion, corner_radius(frame))
    if turn is not None:
        raise DatasetError(frame.source or frame.image, f"{frame.where} distortion",
                           f"{names}: the lens model turns back at radius {turn:.3g} (normalised), inside the "
                           f"image (corners at {corner_radius(frame):.3g}): undistorting would fold the image")
    zoom = intrinsics[0] / frame.fx
    if not 1.0 / MAX_ZOOM <= zoom <= MAX_ZOOM:
        raise DatasetError(frame.source or frame.image, f"{frame.where} distortion",
                           f"{names}: undistorting would scale the image by {zoom:.3g} (expected a lens model "
                           f"that changes it by at most {MAX_ZOOM:g}×)")


def cache_key(frame: Frame, linear: bool) -> str:
    """16 hex digits of SHA-256 over the image (and mask) bytes, the intrinsics, the
    distortion coefficients, the ``linear`` flag and :data:`CACHE_VERSION`."""
    digest = hashlib.sha256()
    for path in (frame.image, frame.mask):
        if path is not None:
            with open(path, "rb") as f:
                for chunk in iter(lambda: f.read(1 << 20), b""):
                    digest.update(chunk)
        digest.update(b"\0")
    params = (CACHE_VERSION, frame.width, frame.height, frame.fx, frame.fy, frame.cx, frame.cy,
              tuple(frame.distortion), bool(linear))
    digest.update(repr(params).encode())
    return digest.hexdigest()[:16]


def pinhole_intrinsics(frame: Frame) -> tuple[float, float, float, float]:
    """(fx″, fy″, cx″, cy″) of the undistorted image, by the formula of the module docstring
    (pixel-corner origin)."""
    w, h = frame.width, frame.height
    k = opencv_matrix(frame.fx, frame.fy, frame.cx, frame.cy)
    new, _ = cv2.getOptimalNewCameraMatrix(k, np.asarray(frame.distortion, np.float64), (w, h), 0, (w, h))
    fx1, fy1, cx1, cy1 = new[0, 0], new[1, 1], new[0, 2] + 0.5, new[1, 2] + 0.5
    s = max(fx1 / frame.fx, fy1 / frame.fy)
    fx2, fy2 = s * frame.fx, s * frame.fy
    x_mid = 0.5 * ((0.5 - cx1) + (w - 0.5 - cx1)) / fx1
    y_mid = 0.5 * ((0.5 - cy1) + (h - 0.5 - cy1)) / fy1
    return float(fx2), float(fy2), float(0.5 * w - fx2 * x_mid), float(0.5 * h - fy2 * y_mid)


def undistortion_maps(frame: Frame, intrinsics: tuple) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV's (map_x, map_y): for each pixel of the pinhole image, where to sample the
    photograph."""
    k = opencv_matrix(frame.fx, frame.fy, frame.cx, frame.cy)
    return cv2.initUndistortRectifyMap(k, np.asarray(frame.distortion, np.float64), None,
                                       opencv_matrix(*intrinsics), (frame.width, frame.height), cv2.CV_32FC1)


def remap(image: np.ndarray, maps: tuple) -> np.ndarray:
    """``image`` (H, W) or (H, W, C) sampled bilinearly at ``maps`` (edge pixels repeated)."""
    out = cv2.remap(np.ascontiguousarray(image, np.float32), maps[0], maps[1], cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_REPLICATE)
    return out.reshape(maps[0].shape + image.shape[2:])


def check_size(array: np.ndarray, frame: Frame, path: Path, what: str):
    """A :class:`DatasetError` when ``array`` is not the frame's width × height."""
    if array.shape[:2] != (frame.height, frame.width):
        raise DatasetError(path, frame.where, f"{what} is {array.shape[1]}×{array.shape[0]}, "
                                              f"expected {frame.width}×{frame.height}")


def undistort_frame(frame: Frame, cache, *, linear: bool = False) -> Frame:
    """``frame`` itself when it has no distortion; else a frame whose image (and mask) are the
    cached undistorted EXR files and whose intrinsics are the pinhole ones, distortion ()."""
    if not frame.distortion:
        return frame
    cache = Path(cache)
    intrinsics = pinhole_intrinsics(frame)
    check_lens(frame, intrinsics)
    stem = f"{Path(frame.image).stem}-{cache_key(frame, linear)}"
    image_out = cache / f"{stem}.exr"
    mask_out = cache / f"{stem}.mask.exr" if frame.mask is not None else None
    fx, fy, cx, cy = intrinsics
    result = replace(frame, image=image_out, mask=mask_out, fx=fx, fy=fy, cx=cx, cy=cy, distortion=())
    if image_out.is_file() and (mask_out is None or mask_out.is_file()):
        return result
    maps = undistortion_maps(frame, intrinsics)
    rgb, alpha = read_image(frame.image, linear=linear, where=frame.where)
    check_size(rgb, frame, frame.image, "image")
    if mask_out is not None:
        mask = read_mask(frame.mask, where=frame.where)
        check_size(mask, frame, frame.mask, "mask")
        write_exr(mask_out, {"Y": np.clip(remap(mask, maps), 0.0, 1.0)})
    if alpha is None:
        out = remap(rgb, maps)
        write_exr(image_out, {c: out[..., i] for i, c in enumerate("RGB")})
    else:
        out = remap(np.concatenate([rgb * alpha[..., None], alpha[..., None]], axis=-1), maps)
        out[..., 3] = np.clip(out[..., 3], 0.0, 1.0)
        write_exr(image_out, {c: out[..., i] for i, c in enumerate("RGBA")})
    return result
