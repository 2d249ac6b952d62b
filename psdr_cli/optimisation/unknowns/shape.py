"""The shape: the object's vertices V through the "large steps" latent u = (I + λL) x (Nicolet et
al. 2021, ``mi.ad.LargeSteps``), V = solve(u), Adam entry ``u`` at ``optimize.learning_rate``.
Owns the object's vertex buffer in the scene and the scene's own copy of its mesh; its checkpoint
file is the mesh (``checkpoints/iter_NNNN.ply``, in the user's coordinates)."""
from __future__ import annotations

import numpy as np
import drjit as dr
import mitsuba as mi

from ...experiment.dataset_frame import to_dataset
from ...run_folder.checkpoints import Mesh
from ...support.jitarray import jit_array
from ..stages import stage_value
from .unknown import Saved, Start, Unknown, detached


class LargeStepsShape(Unknown):
    """The shape being optimised (module docstring)."""
    name = "shape"

    @staticmethod
    def wanted(cfg) -> bool:
        return True

    def __init__(self, start: Start):
        super().__init__(start)
        shape, params = start.shape, start.params
        self.key = f"{start.cfg.object}.vertex_positions"
        self.F = np.asarray(shape.F, np.int64)
        self.uv = None if shape.uv is None else np.asarray(shape.uv, np.float64)
        # LargeSteps welds and orders the vertices by position: a resumed run rebuilds it from the
        # same vertices as the original so that the saved u means the same thing
        self.basis = np.asarray(shape.V if shape.basis is None else shape.basis, np.float64)
        self.steps = mi.ad.LargeSteps(jit_array(mi.Float, self.basis.ravel()), params[f"{start.cfg.object}.faces"],
                                      stage_value(start.cfg.lambda_, start.stage))
        # a resumed run restores u itself: V = solve(u) is then bit-identical to the saved run's
        start.opt["u"] = jit_array(mi.Float, shape.u) if shape.u is not None else \
            self.steps.to_differential(params[self.key])

    def entries(self) -> dict:
        return {"u": (self.start.opt, "u")}

    def scene_values(self) -> dict:
        """V = solve(u)."""
        return {self.key: self.steps.from_differential(self.start.opt["u"])}

    def after_write(self, scene):
        """The scene's copy of the object's mesh (its edges are built from it)."""
        self.mesh_written(scene, self.vertices())

    def mesh_written(self, scene, V):
        obj = scene.objects[self.start.cfg.object]
        obj.vertices, obj.faces = V, self.F

    def write_saved(self, saved: Saved):
        self.start.params[self.key] = jit_array(mi.Float, np.ravel(saved.V))
        self.mesh_written(self.start.scene, np.asarray(saved.V, np.float64))

    def vertices(self) -> np.ndarray:
        """(n, 3) the vertices as the scene holds them."""
        return np.asarray(dr.detach(self.start.params[self.key]), np.float64).reshape(-1, 3)

    def latent(self) -> np.ndarray:
        """u as saved (float32)."""
        return np.asarray(self.start.opt["u"], np.float32)

    def checkpoint_files(self, files, iteration: int) -> list:
        """The checkpoint mesh, in the dataset's coordinates with a camera dataset."""
        dataset = self.start.cfg.target_dataset
        V = to_dataset(self.vertices(), dataset.frame if dataset else None)
        return [Mesh(files.checkpoint(iteration), V, self.F, self.uv)]

    def detach(self):
        detached(self.start.params, self.key)


UNKNOWN = LargeStepsShape
