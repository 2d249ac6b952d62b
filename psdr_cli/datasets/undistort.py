"""Removing lens distortion once, into a cache folder.

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
written to a temporary name and renamed into place (:func:`psdr_cli.fileio.write_exr`). When
both already exist they are reused as they are.
"""
from __future__ import annotations

import hashlib
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from ..fileio import write_exr
from .frames import DatasetError, Frame, opencv_matrix
from .images import read_image, read_mask

#: Bumped when the cached files would come out differently.
CACHE_VERSION = 1


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
