"""``optimize.cameras``: every training view's pose correction
(:class:`psdr_cli.optimisation.camera_refinement.CameraCorrections`: its own Adam, schedule, stops
and gauge), Adam entries and saved values ``camera_<part>`` (and ``camera_stopped``). Owns the
sensors' transforms; its checkpoint files are ``cameras.json`` and the refined cameras in the
dataset's format (:mod:`psdr_cli.run_folder.refined_cameras`)."""
from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from ...datasets.frames import Frame
from ...errors import PsdrError, PsdrWarning
from ...estimators.camera import Projection
from ...experiment.dataset_frame import dataset_frames
from ...rendering.camera_motion import check_camera_motion, with_all_edges
from ...run_folder.checkpoints import CameraPoses
from ...run_folder.refined_cameras import input_format, refined_poses, refocused
from ..camera_refinement import OPENCV_FLIP, CameraCorrections
from .unknown import At, Saved, Start, Unknown


class Cameras(Unknown):
    """The views' pose corrections (module docstring). A moving camera moves every discontinuity
    it sees, so every object's edges take part in the boundary terms; a shape without an edge
    list in view is refused (:mod:`psdr_cli.rendering.camera_motion`)."""
    name = "cameras"
    leaf_form = False
    keeps_moments = True  # the poses' unknowns are the same after a remesh

    @staticmethod
    def wanted(cfg) -> bool:
        return cfg.cameras.mode == "on"

    def __init__(self, start: Start):
        super().__init__(start)
        scene = start.scene
        with_all_edges(scene)
        for view in range(len(scene.sensors)):
            try:
                check_camera_motion(scene, view)
            except PsdrError as exc:
                raise PsdrError(f"{start.file}: optimize.cameras: {str(exc).split(': ', 1)[-1]}; set "
                                f"optimize.cameras: off") from None
        try:
            self.corrections = CameraCorrections(start.cfg.cameras, start.params, len(scene.sensors), start.values)
        except PsdrError as exc:  # optimize.cameras.focal on a camera it cannot scale
            raise PsdrError(f"{start.file}: {exc}") from None

    def entries(self) -> dict:
        opt = self.corrections.opt
        return {f"camera_{k}": (opt, k) for k in opt.keys()}

    def begin(self, iteration: int, total: int) -> bool:
        """The poses move (their transforms carry the corrections' AD graph) from the schedule's start on."""
        moving = self.corrections.refining(iteration, total)
        changed = self.corrections.attached != moving
        self.corrections.attached = moving
        return changed

    def scene_values(self) -> dict:
        return self.corrections.scene_values()

    def after_write(self, scene):
        """The focal factors ride on the sensors, not in their parameters."""
        self.corrections.attach_focal()

    def write_saved(self, saved: Saved):
        """The poses the saved ``values`` hold."""
        self.corrections.write(self.start.params, saved.values)

    def step(self, at: At):
        """Its own Adam step, the stops and the gauge, while the poses move."""
        if self.corrections.attached:
            self.corrections.step(at.iteration, at.total, at.warn)

    def values(self) -> dict:
        return self.corrections.values()

    def checkpoint_files(self, files, iteration: int) -> list:
        cams, dataset = self.corrections, self.start.cfg.target_dataset
        if dataset is not None:
            with warnings.catch_warnings():  # the dataset's warnings were given when the run read it
                warnings.simplefilter("ignore", PsdrWarning)
                frames = dataset_frames(dataset, "train")[1]
            poses = refined_poses([f.cam_to_world for f in frames], cams.initial, cams.matrices(), dataset.frame)
            kind, fmt = "dataset", input_format(frames)
            frames = refocused(frames, cams.focal_scales())  # optimize.cameras.focal
        else:
            frames = [scene_frame(self.start.scene.sensors[v], v) for v in range(cams.views)]
            poses = [M @ OPENCV_FLIP for M in cams.matrices()]
            kind, fmt = "scene", None
        rotation, translation = cams.errors()
        return [CameraPoses(frames, poses, {"rotation": rotation, "translation": translation,
                                            "stopped": cams.stopped,
                                            "focal": cams.focal_scales() if cams.focal else None}, kind, fmt)]

    def summary(self, files) -> dict:
        return {"cameras": str(files.root / "cameras.json")}

    def detach(self):
        self.corrections.detach(self.start.params)


def scene_frame(sensor, view: int) -> Frame:
    """A :class:`~psdr_cli.datasets.frames.Frame` of a scene's camera (no image): its intrinsics in pixels."""
    proj = Projection(sensor)
    f = proj.width / (2 * proj.tan_half)
    return Frame(name=f"camera {view}", image=Path(""), mask=None, cam_to_world=np.eye(4), fx=f, fy=f,
                 cx=proj.width * proj.centre[0], cy=proj.height * proj.centre[1], width=proj.width, height=proj.height)


UNKNOWN = Cameras
