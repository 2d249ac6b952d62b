"""``optimize.albedo``: the object's diffuse reflectance (or principled base colour), one value or,
with ``texture: [W, H]``, an (H, W, 3) bitmap; Adam entry and saved value ``albedo``, written into
the scene clipped to [0, 1]. Owns that BSDF parameter; a texture's checkpoint files are
``albedo.exr``, ``albedo.png`` and ``previews/iter_NNNN_albedo.png``; exported as the asset's
texture or colour."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from ...errors import PsdrError
from ...run_folder.checkpoints import Picture
from ...scene.material_params import texture_experiment
from ...support.jitarray import jit_array
from .asset import object_color
from .unknown import Saved, Start, Unknown, detached


def is_texture(cfg) -> bool:
    """Whether ``optimize.albedo`` is a texture."""
    return bool(cfg.albedo and cfg.albedo_texture is not None)


class Albedo(Unknown):
    """The albedo being recovered (module docstring)."""
    name = "albedo"

    @staticmethod
    def wanted(cfg) -> bool:
        return bool(cfg.albedo)

    @classmethod
    def staged(cls, built, start: Start):
        """For a texture: the object's bitmap holding the saved texture, else the initial colour."""
        cfg = start.cfg
        if not is_texture(cfg):
            return built
        if start.shape.uv is None:
            raise PsdrError(f"{start.file}: optimize.albedo.texture: the shape being optimised has no UV coordinates")
        init = start.values.get("albedo")
        W, H = cfg.albedo_texture
        if init is not None:
            init = np.asarray(init, np.float64).reshape(H, W, 3)
        else:
            init = np.broadcast_to(np.asarray(cfg.albedo_init or (0.5, 0.5, 0.5), np.float64), (H, W, 3))
        return texture_experiment(built, np.clip(init, 0.0, 1.0))

    def __init__(self, start: Start):
        super().__init__(start)
        cfg, params = start.cfg, start.params
        self.texture = is_texture(cfg)
        suffixes = ("reflectance.data", "base_color.data") if self.texture else \
            ("reflectance.value", "base_color.value")
        keys = [k for k in params.keys() if k.startswith(f"{cfg.object}.bsdf.") and k.endswith(suffixes)]
        if not keys:
            raise PsdrError(f"{start.file}: optimize.albedo: the object's BSDF has no constant "
                            f"reflectance/base_color to optimise (give 'texture: [W, H]' for a bitmap)")
        self.key = keys[0]
        if self.texture:  # the scene holds the initial texture already
            start.opt["albedo"] = self.scene_value(self.image())
        else:
            init = start.values.get("albedo")
            if init is None:
                init = cfg.albedo_init or np.asarray(params[self.key]).ravel()
            start.opt["albedo"] = self.scene_value(init)
        start.opt.set_learning_rate({"albedo": cfg.albedo_learning_rate})

    def scene_value(self, a):
        """The albedo ``a`` (numpy, clipped to [0, 1]) as the scene parameter's type: a texture
        (H, W, 3) tensor, an RGB colour, or a grey value (a grey reflectance stays grey)."""
        a = np.clip(np.asarray(a, np.float64), 0.0, 1.0)
        if self.texture:
            return jit_array(mi.TensorXf, a)
        a = a.ravel()
        if isinstance(self.start.params[self.key], mi.Color3f):  # RGB texture
            return mi.Color3f(*(float(x) for x in np.broadcast_to(a, 3)))
        return mi.Float(float(a.mean()))

    def image(self) -> np.ndarray:
        """The texture being recovered as the scene uses it: (H, W, 3) linear RGB in [0, 1]."""
        return np.asarray(dr.detach(self.start.params[self.key]), np.float64)

    def entries(self) -> dict:
        return {"albedo": (self.start.opt, "albedo")}

    def scene_values(self) -> dict:
        """clip(albedo, 0, 1) (re-assigning the Adam entry instead would reset its moments)."""
        return {self.key: dr.clip(self.start.opt["albedo"], 0.0, 1.0)}

    def write_saved(self, saved: Saved):
        if "albedo" in saved.values:
            self.start.params[self.key] = self.scene_value(saved.values["albedo"])

    def values(self) -> dict:
        x = self.start.opt["albedo"]
        a = np.asarray(x, np.float64)
        return {"albedo": a.reshape(x.shape) if self.texture else a.ravel()}

    def textures(self) -> dict:
        return {"albedo": self.image()} if self.texture else {}

    def checkpoint_files(self, files, iteration: int) -> list:
        if not self.texture:
            return []
        return [Picture(files.albedo, self.image(), png=True, preview="albedo")]

    def summary(self, files) -> dict:
        return {"albedo": str(files.albedo) if self.texture else self.values()["albedo"].tolist()}

    def detach(self):
        detached(self.start.params, self.key)

    @staticmethod
    def export(asset, state, exp, where):
        """The recovered texture (with the state's UVs) or colour, clipped to [0, 1]; without a
        recovered albedo, the experiment's own object colour, else grey."""
        albedo = state.values.get("albedo")
        if albedo is not None and np.ndim(albedo) == 3:
            if state.uv is None:
                raise PsdrError(f"{where}: the run recovered a texture but its state has no UV coordinates")
            asset.uv, asset.texture = np.asarray(state.uv, np.float64), np.clip(np.asarray(albedo, np.float64), 0, 1)
        elif albedo is not None:
            asset.color = tuple(float(c) for c in np.broadcast_to(np.clip(np.ravel(albedo), 0, 1), 3))
        else:
            asset.color = object_color(exp, asset.notes)


UNKNOWN = Albedo
