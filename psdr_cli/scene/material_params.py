"""The BSDF parameters behind ``optimize.material`` (roughness, metallic, specular): which
parameter of the object's BSDF each names, its Mitsuba key, and the scene with a one-channel
bitmap in its place when it is recovered as a texture (``texture: [W, H]``)."""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..config.objects import BitmapConfig, BsdfConfig
from ..config.unknowns import MATERIAL_UNKNOWNS
from ..errors import PsdrError


def object_bsdf(exp):
    """The BSDF configuration of the object being optimised (None for a Mitsuba XML object)."""
    obj = next((o for o in exp.scene.objects if o.name == exp.optimize.object), None)
    return None if obj is None else obj.bsdf


def bsdf_parameter(exp, name: str) -> str:
    """The name of the object's BSDF parameter behind ``optimize.material.NAME`` (``alpha`` of a
    rough conductor or dielectric, ``roughness`` of the principled BSDF, …)."""
    _, names = MATERIAL_UNKNOWNS[name]
    bsdf = object_bsdf(exp)
    if bsdf is None or bsdf.type not in names:
        kinds = ", ".join(sorted(names))
        raise PsdrError(f"{exp.file}: optimize.material.{name}.texture: the object's BSDF "
                        f"'{bsdf.type if bsdf else 'from the XML scene'}' has no {name} texture (use {kinds})")
    return names[bsdf.type]


def material_key(obj: str, file, params, name: str, texture: bool = False) -> tuple:
    """(Mitsuba key, clamp range) of the BSDF parameter of object ``obj`` behind
    ``optimize.material.NAME``: a constant ``roughness``/``alpha``, ``metallic`` or ``specular``
    (``….value`` or the parameter itself), or with ``texture`` the texels of the bitmap put there
    (``….data``); ``file``: the experiment, named in the error."""
    (lo, hi), names = MATERIAL_UNKNOWNS[name]
    prefix = f"{obj}.bsdf."
    ends = [f".{p}.data" for p in set(names.values())] if texture else \
        [e for p in set(names.values()) for e in (f".{p}.value", f".{p}")]
    keys = [k for k in params.keys() if k.startswith(prefix) and k.endswith(tuple(ends))]
    if not keys:
        raise PsdrError(f"{file}: optimize.material.{name}: the object's BSDF has no constant "
                        f"{'/'.join(sorted(set(names.values())))} to optimise (a texture, an anisotropic "
                        f"alpha_u/alpha_v, or a BSDF without it)")
    return keys[0], (lo, hi)


def material_texture_experiment(exp, name: str, texels, lookup: BitmapConfig):
    """``exp`` with the object's BSDF parameter behind ``optimize.material.NAME`` replaced by an
    in-memory one-channel bitmap of ``texels`` (H, W, 1), read raw (linear values), looked up like
    the albedo texture (``lookup``: filter and wrap mode)."""
    if exp.scene.mitsuba is not None:
        raise PsdrError(f"{exp.file}: optimize.material.{name}.texture: not available for objects of a Mitsuba XML scene")
    parameter = bsdf_parameter(exp, name)
    bitmap = replace(lookup, data=np.asarray(texels, np.float32).reshape(*np.shape(texels)[:2], 1), raw=True)
    obj = next(o for o in exp.scene.objects if o.name == exp.optimize.object)
    bsdf = BsdfConfig(obj.bsdf.type, {**obj.bsdf.params, parameter: bitmap})
    objects = [replace(o, bsdf=bsdf) if o.name == obj.name else o for o in exp.scene.objects]
    return replace(exp, scene=replace(exp.scene, objects=objects))


def texture_experiment(exp, texture):
    """``exp`` with the optimised object's reflectance (diffuse) or base colour (principled)
    replaced by an in-memory bitmap holding ``texture`` (H, W, 3) (``optimize.albedo.texture``),
    looked up with the object's own bitmap's ``filter_type`` and ``wrap_mode`` if it has one."""
    if exp.scene.mitsuba is not None:
        raise PsdrError(f"{exp.file}: optimize.albedo.texture: not available for objects of a Mitsuba XML scene")
    obj = next(o for o in exp.scene.objects if o.name == exp.optimize.object)
    name = {"diffuse": "reflectance", "principled": "base_color"}.get(obj.bsdf.type)
    if name is None:
        raise PsdrError(f"{exp.file}: optimize.albedo.texture: the object's BSDF '{obj.bsdf.type}' has no "
                        f"reflectance or base_color (use diffuse or principled)")
    bitmap = replace(texture_lookup(exp), data=np.asarray(texture, np.float32))
    bsdf = BsdfConfig(obj.bsdf.type, {**obj.bsdf.params, name: bitmap})
    objects = [replace(o, bsdf=bsdf) if o.name == obj.name else o for o in exp.scene.objects]
    return replace(exp, scene=replace(exp.scene, objects=objects))


def texture_lookup(exp) -> BitmapConfig:
    """The bitmap settings the recovered texture is looked up with: the object's own bitmap's
    ``filter_type`` and ``wrap_mode`` (file, raw and data cleared), or bilinear and repeat."""
    obj = next(o for o in exp.scene.objects if o.name == exp.optimize.object)
    given = [v for k, v in obj.bsdf.params.items() if k in ("reflectance", "base_color")]
    if given and isinstance(given[0], BitmapConfig):
        return replace(given[0], file=None, raw=False, data=None)
    return BitmapConfig()
