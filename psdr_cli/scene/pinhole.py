"""Cameras from pinhole intrinsics and OpenCV extrinsics (photographs, calibrated datasets).

:func:`pinhole_camera` turns a camera-to-world matrix with OpenCV axes (x right, y down, z
forward) and the intrinsics fx, fy, cx, cy (pixels) of a W×H image into a
:class:`~psdr_cli.config.CameraConfig`, a Mitsuba ``perspective`` sensor (:func:`psdr_cli.scene.build.
sensor_dict`) that sees every world point at the pixel where the pinhole model puts it.

Pixel convention: cx, cy are measured from the top-left *corner* of the image, so the centre of
the top-left pixel is (0.5, 0.5) (Mitsuba's film coordinates). Calibrations in OpenCV's own
convention, where that centre is (0, 0), pass cx + 0.5, cy + 0.5.
"""
from __future__ import annotations

import math

import numpy as np

from ..config.cameras_section import CameraConfig
from ..config.limits import MAX_PRINCIPAL_OFFSET

#: Largest |fx/fy − 1| accepted: psdr's film has square pixels (fy = fx); images with other
#: pixels are to be resampled first.
MAX_ASPECT_ERROR = 0.005


def pinhole_camera(cam_to_world, fx: float, fy: float, cx: float, cy: float, width: int, height: int) -> CameraConfig:
    """A :class:`CameraConfig` for a pinhole camera.

    With R, t the rotation and translation of ``cam_to_world`` (4×4, OpenCV axes):

    - origin = t, target = t + R·[0, 0, 1] (the optical axis), up = −R·[0, 1, 0];
    - fov (horizontal, degrees) = 2·atan(W / (2 fx));
    - principal_point = (½ − cx / W, ½ − cy / H), Mitsuba's ``principal_point_offset_x/y``: its
      principal point is the pixel (W (½ − o_x), H (½ − o_y)) = (cx, cy).

    A world point X then lands on the pixel (fx·x/z + cx, fy·y/z + cy), (x, y, z) = R⁻¹(X − t),
    for fy = fx. Raises ValueError unless |fx/fy − 1| ≤ :data:`MAX_ASPECT_ERROR` (non-square
    pixels: resample the image), R is a rotation (orthonormal, det +1; to 1e-4), fx, fy > 0,
    W, H ≥ 1, everything finite, and the principal point lies within ±MAX_PRINCIPAL_OFFSET of
    the film's centre (fractions of W and H; ``scene.cameras[].principal_point``).
    """
    M = np.asarray(cam_to_world, dtype=np.float64)
    if M.shape != (4, 4) or not np.isfinite(M).all():
        raise ValueError(f"cam_to_world: expected a finite 4×4 matrix, got shape {M.shape}")
    values = {"fx": fx, "fy": fy, "cx": cx, "cy": cy}
    for name, v in values.items():
        if not math.isfinite(float(v)):
            raise ValueError(f"{name}: expected a finite number, got {v}")
    if int(width) != width or int(height) != height or width < 1 or height < 1:
        raise ValueError(f"width, height: expected integers >= 1, got {width}, {height}")
    if not (fx > 0 and fy > 0):
        raise ValueError(f"fx, fy: expected focal lengths > 0 (pixels), got {fx}, {fy}")
    if abs(fx / fy - 1) > MAX_ASPECT_ERROR:
        raise ValueError(f"fx/fy = {fx / fy:.6g}: psdr's pixels are square (|fx/fy - 1| <= {MAX_ASPECT_ERROR}); "
                         f"resample the image first")
    R, t = M[:3, :3], M[:3, 3]
    if not np.allclose(R.T @ R, np.eye(3), atol=1e-4) or np.linalg.det(R) <= 0:
        raise ValueError("cam_to_world: its 3×3 part is not a rotation (orthonormal, determinant +1)")
    offset = (0.5 - cx / width, 0.5 - cy / height)
    if max(abs(o) for o in offset) > MAX_PRINCIPAL_OFFSET:
        raise ValueError(f"cx, cy = {cx}, {cy}: the principal point is more than {MAX_PRINCIPAL_OFFSET:g} film "
                         f"widths/heights from the centre of the {width}×{height} image")
    forward, down = R[:, 2], R[:, 1]
    return CameraConfig(origin=tuple(float(c) for c in t), target=tuple(float(c) for c in t + forward),
                        up=tuple(float(c) for c in -down), fov=math.degrees(2 * math.atan(width / (2 * fx))),
                        principal_point=tuple(float(o) for o in offset))
