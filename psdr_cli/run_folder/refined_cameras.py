"""The refined cameras of a run (``optimize.cameras``), written as data a user can take elsewhere:

- ``cameras.json``: every training view's name, image, camera-to-world matrix (OpenCV axes:
  x right, y down, z forward; in the dataset's coordinates, or the scene's without a dataset),
  its intrinsics (the dataset's, with ``optimize.cameras.focal`` its focal lengths f_x, f_y
  times the refined scale s: the principal point is kept), and the correction applied
  (degrees, camera distances, the focal scale) and whether its refinement stopped;
- ``refined_cameras/``: the same poses in the input's own format, with the images named as the
  input names them (relative paths from this folder, or the original image folder for COLMAP):
  ``transforms_train.json`` (Blender / NeRF-synthetic), ``transforms.json`` (instant-ngp,
  nerfstudio; with each frame's ``mask_path`` when it had one) or a COLMAP text model
  ``sparse/0/{cameras,images,points3D}.txt``. The poses are in the world the dataset's cameras
  were read in: a nerfstudio ``applied_transform`` has been undone, and none is written.

A refined pose is the dataset's pose with the correction carried into its frame: with S the
similarity x ↦ s(x − c) of the normalised frame and ΔM = M · M⁰⁻¹ the correction of the
camera-to-world transform found there, the dataset's pose becomes S⁻¹ ΔM S · C (C the pose read).
Every file is written atomically.
"""
from __future__ import annotations

import os
from dataclasses import replace
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from ..support import fileio

#: OpenGL camera axes (x right, y up, z backward) from OpenCV's, and back (its own inverse).
OPENCV_TO_OPENGL = np.diag([1.0, -1.0, -1.0, 1.0])


def similarity(frame) -> np.ndarray:
    """S (4×4) of the normalised frame x_n = s(x − c) (``frame`` = (s, c); None: the identity)."""
    S = np.eye(4)
    if frame is not None:
        s, c = frame
        S[:3, :3] *= s
        S[:3, 3] = -s * np.asarray(c, np.float64)
    return S


def refined_poses(poses, initial, corrected, frame) -> list:
    """The refined camera-to-world matrices S⁻¹ (M M⁰⁻¹) S · C of each pose C (module docstring);
    ``initial``, ``corrected``: the scene's transforms before and after the corrections."""
    S = similarity(frame)
    S_inv = np.linalg.inv(S)
    out = []
    for C, M0, M in zip(poses, initial, corrected):
        delta = S_inv @ M @ np.linalg.inv(M0) @ S
        U, _, Vt = np.linalg.svd(delta[:3, :3])  # float32 round-off: the nearest rotation
        delta[:3, :3] = U @ Vt
        out.append(delta @ np.asarray(C, np.float64))
    return out


def refocused(frames, scales) -> list:
    """``frames`` with their focal lengths f_x, f_y times the refined focal scales (principal
    points kept)."""
    return [replace(f, fx=f.fx * float(s), fy=f.fy * float(s)) for f, s in zip(frames, scales)]


def camera_records(frames, poses, rotation_deg, translation, stopped, focal_scale=None) -> list:
    """The ``views`` entries of cameras.json (``focal_scale``: each view's refined s, or None)."""
    scales = [None] * len(frames) if focal_scale is None else focal_scale
    return [{"name": f.name, "image": str(f.image), "split": f.split,
             "cam_to_world": np.round(P, 12).tolist(), "fx": f.fx, "fy": f.fy, "cx": f.cx, "cy": f.cy,
             "width": f.width, "height": f.height, "distortion": list(f.distortion),
             "correction": {"rotation_deg": float(r), "translation": float(t), "stopped": bool(s),
                            **({} if k is None else {"focal_scale": float(k)})}}
            for f, P, r, t, s, k in zip(frames, poses, rotation_deg, translation, stopped, scales)]


def write_cameras(root: Path, frames, poses, corrections: dict, iteration: int, frame_kind: str,
                  input_format: str | None):
    """cameras.json and (with ``input_format``) ``refined_cameras/`` in that format."""
    records = camera_records(frames, poses, *corrections.values())
    fileio.write_json(root / "cameras.json", {"format": "psdr cameras", "axes": "opencv", "coordinates": frame_kind,
                                              "iteration": iteration, "views": records})
    out = root / "refined_cameras"
    if input_format is None:
        return
    out.mkdir(exist_ok=True)
    if input_format == "colmap":
        write_colmap_text(out / "sparse" / "0", frames, poses)
    elif input_format == "blender":
        fileio.write_json(out / "transforms_train.json", blender_document(out, frames, poses))
    else:
        fileio.write_json(out / "transforms.json", transforms_document(out, frames, poses))


def input_format(frames) -> str:
    """``colmap``, ``blender`` or ``transforms``: the format the frames were read from."""
    source = Path(frames[0].source or "")
    if source.name.startswith("images."):
        return "colmap"
    return "blender" if source.name.startswith("transforms_") else "transforms"


def relative_image(folder: Path, image: Path) -> str:
    """``image`` relative to ``folder`` (POSIX separators), as a JSON dataset's file_path."""
    return Path(os.path.relpath(Path(image).resolve(), folder.resolve())).as_posix()


def opengl_pose(P) -> list:
    return (np.asarray(P, np.float64) @ OPENCV_TO_OPENGL).tolist()


def blender_document(folder: Path, frames, poses) -> dict:
    """A Blender split file: the horizontal field of view and one frame per pose (OpenGL axes)."""
    f = frames[0]
    return {"camera_angle_x": float(2 * np.arctan(0.5 * f.width / f.fx)),
            "frames": [{"file_path": relative_image(folder, fr.image), "transform_matrix": opengl_pose(P)}
                       for fr, P in zip(frames, poses)]}


def transforms_document(folder: Path, frames, poses) -> dict:
    """An instant-ngp / nerfstudio transforms.json: intrinsics and distortion per frame."""
    entries = []
    for fr, P in zip(frames, poses):
        entry = {"file_path": relative_image(folder, fr.image), "transform_matrix": opengl_pose(P),
                 "fl_x": fr.fx, "fl_y": fr.fy, "cx": fr.cx, "cy": fr.cy, "w": fr.width, "h": fr.height}
        entry.update(dict(zip(("k1", "k2", "p1", "p2", "k3"), fr.distortion[:5])))
        if fr.mask is not None:
            entry["mask_path"] = relative_image(folder, fr.mask)
        entries.append(entry)
    return {"frames": entries}


def colmap_camera_line(camera_id: int, f) -> str:
    """cameras.txt line of a frame: PINHOLE, OPENCV (4 coefficients) or FULL_OPENCV (8)."""
    d = list(f.distortion)
    if not d:
        model, params = "PINHOLE", [f.fx, f.fy, f.cx, f.cy]
    elif len(d) == 4:
        model, params = "OPENCV", [f.fx, f.fy, f.cx, f.cy, *d]
    else:
        model, params = "FULL_OPENCV", [f.fx, f.fy, f.cx, f.cy, *(d + [0.0] * (8 - len(d)))]
    return f"{camera_id} {model} {f.width} {f.height} " + " ".join(f"{p:.17g}" for p in params)


def colmap_image_lines(image_id: int, f, P) -> list:
    """images.txt lines of a frame: world-to-camera quaternion (w, x, y, z) and translation, then
    an empty line of 2D points."""
    w2c = np.linalg.inv(np.asarray(P, np.float64))
    x, y, z, w = Rotation.from_matrix(w2c[:3, :3]).as_quat()
    t = w2c[:3, 3]
    numbers = " ".join(f"{v:.17g}" for v in (w, x, y, z, *t))
    return [f"{image_id} {numbers} {image_id} {f.name}", ""]


def write_colmap_text(model: Path, frames, poses):
    """A COLMAP text model of the refined poses: one camera per image, no 3D points."""
    model.mkdir(parents=True, exist_ok=True)
    cameras = ["# Camera list: CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]"]
    images = ["# Image list: IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME; then its 2D points"]
    for k, (f, P) in enumerate(zip(frames, poses), start=1):
        cameras.append(colmap_camera_line(k, f))
        images.extend(colmap_image_lines(k, f, P))
    for name, lines in (("cameras.txt", cameras), ("images.txt", images), ("points3D.txt", ["# no 3D points"])):
        with fileio.atomic_path(model / name) as tmp:
            tmp.write_text("\n".join(lines) + "\n")
