"""The cameras the viewer draws: each one's pose (camera-to-world, OpenCV axes: x right, y down,
z forward), vertical field of view, aspect, thumbnail and whether it is held out, made from an
experiment's camera configs, a dataset's frames, a run's cameras.json or its targets' EXR
headers. Reads files only through the callers' paths; writes nothing."""
from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..support import fileio
from .pictures import read_png, thumbnail


@dataclass
class ViewCamera:
    """One camera as drawn: ``pose`` (4, 4) camera-to-world in OpenCV axes, ``fov`` the vertical
    field of view in radians, ``aspect`` width / height, ``image`` an 8-bit RGB thumbnail or None."""
    name: str
    pose: np.ndarray
    fov: float
    aspect: float
    image: np.ndarray | None = None
    held_out: bool = False


def look_at_pose(origin, target, up) -> np.ndarray:
    """Camera-to-world (OpenCV axes) of a camera at ``origin`` looking at ``target`` with ``up``."""
    origin, target, up = (np.asarray(x, np.float64) for x in (origin, target, up))
    forward = target - origin
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = right, down, forward, origin
    return pose


def vertical_fov(horizontal_deg: float, aspect: float) -> float:
    """The vertical field of view (radians) of a horizontal one in degrees at ``aspect`` = W / H."""
    return 2 * math.atan(math.tan(math.radians(horizontal_deg) / 2) / aspect)


def config_camera(name: str, cam, width: int, height: int, image=None) -> ViewCamera:
    """A :class:`~psdr_cli.config.cameras_section.CameraConfig` (horizontal fov) on a ``width`` × ``height`` film."""
    aspect = width / height
    return ViewCamera(name, look_at_pose(cam.origin, cam.target, cam.up), vertical_fov(cam.fov, aspect), aspect, image)


def pinhole_camera(name: str, pose, fy: float, width: int, height: int, image=None, held_out=False) -> ViewCamera:
    """A camera of focal length ``fy`` pixels on a ``width`` × ``height`` film at ``pose`` (OpenCV)."""
    return ViewCamera(name, np.asarray(pose, np.float64), 2 * math.atan(0.5 * height / fy), width / height,
                      image, held_out)


def cameras_json(path: Path) -> list:
    """The cameras of a run's cameras.json (the refined poses; the ``test`` split held out), with
    the photographs as thumbnails when they can be read."""
    views = json.loads(Path(path).read_text())["views"]
    out = []
    for v in views:
        picture = read_png(Path(v["image"])) if v.get("image") else None
        out.append(pinhole_camera(v["name"], v["cam_to_world"], float(v["fy"]), int(v["width"]), int(v["height"]),
                                  None if picture is None else thumbnail(picture), v.get("split") == "test"))
    return out


def target_cameras(targets: Path) -> list:
    """The cameras of a run's cached targets (``targets/view_NNN.exr``, their ``psdr.camera``
    headers), with the targets' PNG previews as thumbnails."""
    out = []
    for exr in sorted(Path(targets).glob("view_[0-9][0-9][0-9].exr")):
        try:
            header = fileio.read_exr(exr)["__header__"]
            cam = header["psdr.camera"]
            cam = json.loads(cam) if isinstance(cam, str) else cam
            height, width = fileio.read_rgb_exr(exr).shape[:2]
        except Exception:  # noqa: BLE001  (a torn or foreign file: that camera is not drawn)
            continue
        picture = read_png(exr.with_suffix(".png"))
        aspect = width / height
        out.append(ViewCamera(exr.stem, look_at_pose(cam["origin"], cam["target"], cam["up"]),
                              vertical_fov(float(cam["fov"]), aspect), aspect,
                              None if picture is None else thumbnail(picture)))
    return out


def up_direction(cameras: list) -> np.ndarray:
    """The scene's up direction as the cameras see it: the mean of their up axes (+z without cameras)."""
    if not cameras:
        return np.array([0.0, 0.0, 1.0])
    up = -np.mean([c.pose[:3, 1] for c in cameras], axis=0)
    n = np.linalg.norm(up)
    return up / n if n > 1e-6 else np.array([0.0, 0.0, 1.0])
