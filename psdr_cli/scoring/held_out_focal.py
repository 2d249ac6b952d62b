"""The focal lengths a run refined (``optimize.cameras.focal``) carried to its held-out cameras.

A held-out photograph taken with the same camera as training views has their focal length: a
held-out camera whose intrinsics (f_x, c_x, c_y, width, height, as the dataset gives them) are a
training camera model's gets that model's refined scale s, its horizontal field of view becoming
2 atan(tan(φ/2) / s) (the principal point kept). The scales come from the run's ``cameras.json``
(each training view's refined f_x = s·f_x and its ``focal_scale`` s). Reads that file and the
dataset's frames; writes nothing.
"""
from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

from ..experiment.dataset_frame import dataset_frames
from ..scene.sensors import scaled_fov

#: Relative tolerance within which two cameras' intrinsics are the same camera model.
SAME_MODEL = 1e-6


def model_scales(cameras_json: Path) -> list:
    """[(f_x, c_x, c_y, width, height, s)] of every training view of ``cameras_json`` that records a
    refined focal scale s, with f_x as the dataset gave it (the refined one over s); [] without."""
    views = json.loads(Path(cameras_json).read_text()).get("views", [])
    out = []
    for v in views:
        s = v.get("correction", {}).get("focal_scale")
        if s is not None and v.get("split", "train") == "train":
            out.append((v["fx"] / s, v["cx"], v["cy"], v["width"], v["height"], float(s)))
    return out


def same_model(frame, model) -> bool:
    """Whether ``frame``'s intrinsics are those of ``model`` (:func:`model_scales`' entries)."""
    fx, cx, cy, width, height, _ = model
    return (frame.width, frame.height) == (width, height) and abs(frame.fx - fx) <= SAME_MODEL * fx and \
        max(abs(frame.cx - cx), abs(frame.cy - cy)) <= SAME_MODEL * width


def refocused_held_out(test, cameras_json) -> tuple:
    """(experiment, scales): ``test`` (the held-out split's experiment, its cameras in the order
    of the dataset's held-out frames) with every camera of a refined model at that model's focal
    length, and the scale each camera got (1 where none applies: no ``cameras.json``, no refined
    focal length, or intrinsics no training view has)."""
    models = model_scales(cameras_json) if cameras_json and Path(cameras_json).is_file() else []
    count = len(test.scene.cameras)
    if not models:
        return test, [1.0] * count
    _, frames = dataset_frames(test.optimize.target_dataset, "test")
    scales = [next((m[5] for m in models if same_model(f, m)), 1.0) for f in frames]
    cameras = [replace(c, fov=scaled_fov(c.fov, s)) if s != 1.0 else c for c, s in zip(test.scene.cameras, scales)]
    return replace(test, scene=replace(test.scene, cameras=cameras)), scales
