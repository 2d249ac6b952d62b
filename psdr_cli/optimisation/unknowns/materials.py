"""``optimize.material``: BSDF parameters of the object (roughness or α, metallic, specular:
:data:`psdr_cli.config.unknowns.MATERIAL_UNKNOWNS`), each one value or, with ``texture: [W, H]``,
an (H, W, 1) bitmap, clamped to its range after every step; Adam entry and saved value by the
parameter's name. Owns those BSDF parameters; a texture's checkpoint files are ``NAME.exr`` and
``NAME.png`` (grey); exported as glTF metallic-roughness factors or maps and MTL PBR values."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from ...config.unknowns import MATERIAL_DEFAULTS, MATERIAL_UNKNOWNS
from ...errors import PsdrError
from ...run_folder.checkpoints import Picture
from ...scene.material_params import bsdf_parameter, material_key, material_texture_experiment, object_bsdf
from ...support.jitarray import jit_array
from .asset import PBR_PNG, run_object
from .unknown import Saved, Start, Unknown, detached


class Materials(Unknown):
    """The BSDF parameters being recovered (module docstring)."""
    name = "materials"

    @staticmethod
    def wanted(cfg) -> bool:
        return bool(cfg.material)

    @classmethod
    def staged(cls, built, start: Start):
        """Each texture's bitmap holding its saved texels, else its initial value
        (:func:`initial_texels`)."""
        textures = [m for m in start.cfg.material if m.texture is not None]
        if textures and start.shape.uv is None:
            raise PsdrError(f"{start.file}: optimize.material.{textures[0].name}.texture: the shape being optimised "
                            f"has no UV coordinates")
        for m in textures:
            built = material_texture_experiment(built, m.name, initial_texels(start.source, m, start.values.get(m.name)),
                                                start.lookup)
        return built

    def __init__(self, start: Start):
        super().__init__(start)
        self.keys = {}  # name -> (scene key, (lo, hi))
        self.texture_sizes = {m.name: m.texture for m in start.cfg.material if m.texture is not None}
        for m in start.cfg.material:
            self.add(m)

    def add(self, m):
        """``optimize.material.NAME``: a constant or a texture (the scene holds its initial texels
        already), within its range."""
        start = self.start
        key, (lo, hi) = material_key(start.cfg.object, start.file, start.params, m.name, texture=m.texture is not None)
        self.keys[m.name] = key, (lo, hi)
        if m.texture is not None:
            start.opt[m.name] = dr.clip(mi.TensorXf(start.params[key]), lo, hi)
        else:
            init = start.values.get(m.name)
            init = float(np.ravel(init)[0]) if init is not None else \
                (m.init if m.init is not None else float(np.ravel(start.params[key])[0]))
            start.opt[m.name] = mi.Float(min(max(init, lo), hi))
        start.opt.set_learning_rate({m.name: m.learning_rate})

    def entries(self) -> dict:
        return {name: (self.start.opt, name) for name in self.keys}

    def scene_values(self) -> dict:
        """Each parameter as it is (within its range: :meth:`step` clamps it)."""
        return {key: self.start.opt[name] for name, (key, _) in self.keys.items()}

    def write_saved(self, saved: Saved):
        params, values = self.start.params, saved.values
        for name, (key, _) in self.keys.items():
            if name in values and name in self.texture_sizes:
                W, H = self.texture_sizes[name]
                params[key] = jit_array(mi.TensorXf, np.asarray(values[name], np.float64).reshape(H, W, 1))
            elif name in values:
                params[key] = mi.Float(float(np.ravel(values[name])[0]))

    def step(self, at):
        """Each parameter clamped to its range (Adam's moments kept)."""
        for name, (_, (lo, hi)) in self.keys.items():
            self.start.opt[name] = dr.clip(self.start.opt[name], lo, hi)

    def values(self) -> dict:
        out = {}
        for name in self.keys:
            x = self.start.opt[name]
            v = np.asarray(x, np.float64)
            out[name] = v.reshape(x.shape) if name in self.texture_sizes else v.ravel()
        return out

    def image(self, name: str) -> np.ndarray:
        """The texture of ``optimize.material.NAME`` as the scene uses it: (H, W, 1) in its range."""
        return np.asarray(dr.detach(self.start.params[self.keys[name][0]]), np.float64)

    def textures(self) -> dict:
        return {name: self.image(name) for name in self.texture_sizes}

    def checkpoint_files(self, files, iteration: int) -> list:
        """Each texture as a grey EXR and PNG."""
        return [Picture(files.material(name), np.repeat(self.image(name), 3, axis=-1), png=True)
                for name in self.texture_sizes]

    def summary(self, files) -> dict:
        values = self.values()
        return {name: str(files.material(name)) if name in self.texture_sizes else values[name].tolist()
                for name in self.keys}

    def detach(self):
        for key, _ in self.keys.values():
            detached(self.start.params, key)

    @staticmethod
    def export(asset, state, exp, where):
        """The glTF metallic and roughness factors, or maps with the state's UVs, of the recovered
        values (a principled roughness as it is, a rough conductor's or dielectric's α as √α; the
        defaults, 0 and 1, for those not recovered); every recovered value in ``export.json``."""
        values = state.values
        if any(np.ndim(values.get(k)) == 3 for k in PBR_PNG) and asset.uv is None:
            if state.uv is None:
                raise PsdrError(f"{where}: the run recovered a material texture but its state has no UV coordinates")
            asset.uv = np.asarray(state.uv, np.float64)
        obj = run_object(exp)
        principled = obj is None or obj.bsdf.type == "principled"
        for name in ("roughness", "metallic"):
            if values.get(name) is None:
                continue
            v = np.clip(np.asarray(values[name], np.float64), 0, 1)
            v = v if name == "metallic" or principled else np.sqrt(v)  # glTF roughness of an α
            if v.ndim == 3:
                asset.maps[name] = v[..., 0]
                asset.record[name] = PBR_PNG[name]
            else:
                setattr(asset, name, float(v.ravel()[0]))
                asset.record[name] = float(np.ravel(values[name])[0])
        if values.get("specular") is not None:
            asset.record["specular"] = float(np.ravel(values["specular"])[0])


def initial_texels(exp, m, saved) -> np.ndarray:
    """(H, W, 1) starting texels of the texture of ``optimize.material.NAME`` (``m``): the saved
    ones, else ``init``, the BSDF's own constant or Mitsuba's default, clamped to its range."""
    W, H = m.texture
    (lo, hi), _ = MATERIAL_UNKNOWNS[m.name]
    if saved is not None:
        return np.clip(np.asarray(saved, np.float64).reshape(H, W, 1), lo, hi)
    parameter = bsdf_parameter(exp, m.name)
    given = object_bsdf(exp).params.get(parameter)
    value = m.init if m.init is not None else given if isinstance(given, (int, float)) else MATERIAL_DEFAULTS[parameter]
    return np.full((H, W, 1), min(max(float(value), lo), hi))


UNKNOWN = Materials
