"""``scene.objects``: each object's mesh (a file, an OBJ part or a procedural shape), transform,
BSDF (with bitmap textures) and per-part overrides."""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .limits import FLOAT32_MAX, MAX_COORD
from .scene_ids import name_problem
from .values import Parser, Section, boolean, choice, describe, integer, number, path_relative_to, scale3, string, unit, vector


@dataclass
class MeshSpec:
    key: str
    file: Path | None = None
    shape: str | None = None   # a procedural shape, or "mitsuba" for a mesh of an XML scene
    params: dict = field(default_factory=dict)
    repair: bool = False
    part: str | None = None    # one group/object of an OBJ file
    split: bool = False        # one scene object per group/object of an OBJ file


@dataclass
class TransformConfig:
    translate: tuple = (0.0, 0.0, 0.0)
    rotate_axis: tuple = (0.0, 0.0, 1.0)
    rotate_deg: float = 0.0
    scale: tuple = (1.0, 1.0, 1.0)


@dataclass
class BitmapConfig:
    """A bitmap texture as a BSDF parameter value (Mitsuba's ``bitmap``): an image file (PNG, EXR,
    JPG) looked up at the mesh's UV coordinates, or (``data``, not a YAML key) an in-memory
    (H, W, 3) linear float image, e.g. the texture an optimisation is recovering."""
    file: Path | None = None
    filter_type: str = "bilinear"
    wrap_mode: str = "repeat"
    raw: bool = False
    data: Any = None


@dataclass
class BsdfConfig:
    type: str = "diffuse"
    params: dict = field(default_factory=dict)


@dataclass
class ObjectConfig:
    name: str
    mesh: MeshSpec
    key: str
    transform: TransformConfig = field(default_factory=TransformConfig)
    bsdf: BsdfConfig = field(default_factory=BsdfConfig)
    edges: bool = True
    smooth: bool = False
    bsdf_given: bool = True     # False: the default BSDF, which an OBJ part's MTL colour replaces (then True)
    parts: dict = field(default_factory=dict)  # split objects: part name -> {bsdf, edges, smooth} overrides


BSDF_PARAMS = {
    "diffuse": ("reflectance",),
    "roughconductor": ("material", "eta", "k", "specular_reflectance", "distribution", "alpha",
                       "alpha_u", "alpha_v", "sample_visible"),
    "roughdielectric": ("int_ior", "ext_ior", "specular_reflectance", "specular_transmittance",
                        "distribution", "alpha", "alpha_u", "alpha_v", "sample_visible"),
    "principled": ("base_color", "roughness", "metallic", "specular", "spec_tint", "anisotropic",
                   "sheen", "sheen_tint", "clearcoat", "clearcoat_gloss", "spec_trans", "eta"),
}
SHAPE_PARAMS = {
    "sphere": {"radius": number(positive=True, maximum=MAX_COORD), "subdivisions": integer(0, 8),
               "resolution": integer(3, 2048), "uv": boolean},
    "plane": {"size": None},
    "cube": {"size": None},
    "torus": {"major_radius": number(positive=True, maximum=MAX_COORD),
              "minor_radius": number(positive=True, maximum=MAX_COORD),
              "major_sections": integer(3, 4096), "minor_sections": integer(3, 4096)},
    "bunny": {"size": number(positive=True, maximum=MAX_COORD), "faces": integer(100, 1_000_000)},
    "eared_blob": {"radius": number(positive=True, maximum=MAX_COORD),
                   "ear_length": number(minimum=0, maximum=MAX_COORD), "ear_width": number(positive=True, maximum=1),
                   "ear_tilt_deg": number(minimum=-80, maximum=80), "subdivisions": integer(2, 7)},
    "grooved_block": {"size": None, "groove_radius": number(positive=True, maximum=MAX_COORD),
                      "segments": integer(2, 4096)},
}

#: Physical range of the numeric BSDF parameters (per channel); the others only need to be finite.
BSDF_RANGES = {name: (0.0, 1.0) for name in (
    "reflectance", "specular_reflectance", "specular_transmittance", "base_color", "roughness", "metallic",
    "specular", "spec_tint", "anisotropic", "sheen", "sheen_tint", "clearcoat", "clearcoat_gloss", "spec_trans",
    "alpha", "alpha_u", "alpha_v")}
BSDF_RANGES.update({name: (1e-3, 10.0) for name in ("eta", "int_ior", "ext_ior")})
BSDF_RANGES["k"] = (0.0, 100.0)

#: Image formats a bitmap texture may be read from (by ``mi.Bitmap``).
BITMAP_FORMATS = (".png", ".exr", ".jpg", ".jpeg")
BITMAP_FILTERS = ("bilinear", "nearest")
BITMAP_WRAPS = ("repeat", "mirror", "clamp")


def parse_bitmap(value, where) -> BitmapConfig:
    """``{type: bitmap, file: image, filter_type, wrap_mode, raw}``; ``file`` is relative to the
    experiment file and must exist, be readable and be a PNG, EXR or JPG image (its texels are
    checked when the scene is built)."""
    sec = Section(value, where)
    sec.get("type", choice("bitmap"))
    file = sec.get("file", path_relative_to(Path(where.file).resolve().parent))
    b = BitmapConfig(file=file,
                     filter_type=sec.get("filter_type", choice(*BITMAP_FILTERS), "bilinear"),
                     wrap_mode=sec.get("wrap_mode", choice(*BITMAP_WRAPS), "repeat"),
                     raw=sec.get("raw", boolean, False))
    sec.done()
    w = where.child("file")
    if file.suffix.lower() not in BITMAP_FORMATS:
        raise w.fail(f"unsupported image format '{file.suffix}' (expected {', '.join(BITMAP_FORMATS)})")
    if not file.is_file():
        raise w.fail(f"texture file not found: {file}")
    if not os.access(file, os.R_OK):
        raise w.fail(f"texture file is not readable: {file}")
    return b


def _bsdf_value(value, where):
    if isinstance(value, str):
        return value
    if isinstance(value, bool):
        return value
    name = where.path.rsplit(".", 1)[-1]
    lo, hi = BSDF_RANGES.get(name, (-MAX_COORD, MAX_COORD))
    if isinstance(value, (int, float)):
        v = number()(value, where)
        values = [v]
    elif isinstance(value, list):
        v = vector(3, bound=FLOAT32_MAX)(value, where)
        values = list(v)
    elif isinstance(value, dict):
        return parse_bitmap(value, where)
    else:
        raise where.fail(f"expected a number, a list of 3 numbers, a string or a bitmap "
                         f"{{type: bitmap, file: ...}}, got {describe(value)}")
    if min(values) < lo or max(values) > hi:
        raise where.fail(f"expected values in [{lo:g}, {hi:g}], got {describe(value)}")
    return v


def parse_bsdf(value, where) -> BsdfConfig:
    sec = Section(value, where)
    kind = sec.get("type", choice(*BSDF_PARAMS))
    params = {}
    for name in BSDF_PARAMS[kind]:
        v = sec.get(name, _bsdf_value, None)
        if v is not None:
            params[name] = v
    sec.done()
    return BsdfConfig(kind, params)


def parse_mesh(base: Path) -> Parser:
    def parse(value, where):
        sec = Section(value, where)
        if sec.has("file") and sec.has("shape"):
            raise where.fail("give either 'file' or 'shape', not both")
        repair = sec.get("repair", boolean, False)
        if sec.has("file"):
            spec = MeshSpec(where.path + ".file", file=sec.get("file", path_relative_to(base)), repair=repair)
            spec.part = sec.get("part", string, None)
            spec.split = sec.get("split", boolean, False)
            sec.done()
            if (spec.part is not None or spec.split) and spec.file.suffix.lower() != ".obj":
                raise where.child("part" if spec.part is not None else "split").fail(
                    f"parts need an .obj file (groups 'g' / objects 'o'), got '{spec.file.name}'")
            if spec.part is not None and spec.split:
                raise where.fail("give either 'part' or 'split: true', not both")
            return spec
        shape = sec.get("shape", choice(*SHAPE_PARAMS), None)
        if shape is None:
            raise where.fail("expected 'file: <path.ply|.obj>' or 'shape: " + "|".join(SHAPE_PARAMS) + "'")
        params = {}
        for name, parser in SHAPE_PARAMS[shape].items():
            if parser is None:  # size of a plane (w, h), a cube or a grooved block (x, y, z)
                parser = _plane_size if shape == "plane" else scale3
            v = sec.get(name, parser, None)
            if v is not None:
                params[name] = v
        sec.done()
        return MeshSpec(where.path, shape=shape, params=params, repair=repair)
    return parse


def object_name(value, where):
    """An object's name: one that cannot be taken for psdr's own ids (:func:`name_problem`)."""
    name = string(value, where)
    problem = name_problem(name)
    if problem:
        raise where.fail(problem)
    return name


def _plane_size(value, where):
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        value = [value, value]
    return vector(2, positive=True)(value, where)


def parse_transform(value, where) -> TransformConfig:
    sec = Section(value, where)
    t = TransformConfig()
    t.translate = sec.get("translate", vector(3), t.translate)
    if sec.has("rotate"):
        rot = Section(sec.get("rotate", lambda v, w: v), where.child("rotate"))
        t.rotate_axis = unit(rot.get("axis", vector(3, nonzero=True)))
        t.rotate_deg = rot.get("angle_deg", number())
        rot.done()
    t.scale = sec.get("scale", scale3, t.scale)
    sec.done()
    return t


def parse_object(base: Path) -> Parser:
    def parse(value, where):
        sec = Section(value, where)
        obj = ObjectConfig(
            name=sec.get("name", object_name),
            mesh=sec.get("mesh", parse_mesh(base)),
            key=where.path,
            transform=sec.get("transform", parse_transform, TransformConfig()),
            bsdf=sec.get("bsdf", parse_bsdf, BsdfConfig("diffuse", {"reflectance": (0.5, 0.5, 0.5)})),
            edges=sec.get("edges", boolean, True),
            smooth=sec.get("smooth", boolean, False),
            bsdf_given=sec.has("bsdf"),
        )
        if sec.has("parts"):
            if not obj.mesh.split:
                raise where.child("parts").fail("only allowed with 'mesh: {file: x.obj, split: true}'")
            obj.parts = sec.get("parts", parse_parts)
        sec.done()
        return obj
    return parse


def parse_parts(value, where) -> dict:
    """``parts: {NAME: {bsdf, edges, smooth}}``: per-part overrides of a split OBJ object."""
    if not isinstance(value, dict):
        raise where.fail(f"expected a mapping of part names, got {describe(value)}")
    out = {}
    for name, entry in value.items():
        w = where.child(str(name))
        sec = Section(entry, w)
        out[str(name)] = {k: v for k, v in (("bsdf", sec.get("bsdf", parse_bsdf, None)),
                                            ("edges", sec.get("edges", boolean, None)),
                                            ("smooth", sec.get("smooth", boolean, None))) if v is not None}
        sec.done()
    return out
