"""Named parts of OBJ files (``o`` objects and ``g`` groups) and their MTL diffuse colours.

An OBJ *part* is the set of faces written after an ``o NAME`` or ``g NAME`` statement, up to the
next one (faces before any such statement form the part ``default``; statements with the same
name add to one part; parts without faces are dropped). A part's material is the ``usemtl``
in effect at its first face; ``Kd`` of that material (from the ``mtllib`` files, relative to the
OBJ) is its diffuse colour. Polygons are split into triangle fans; only positions are read.

``mesh: {file: x.obj, part: NAME}`` reads one part; ``mesh: {file: x.obj, split: true}`` makes one
scene object per part, named ``<object>_<part>`` (:func:`expand_objects`).
"""
from __future__ import annotations

import re
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ..config.objects import BsdfConfig
from ..config.scene_section import SceneConfig
from ..config.values import Where
from ..errors import ConfigError


@dataclass
class ObjPart:
    """One part: its triangles (indices into the file's positions), material name and Kd (read
    from the MTL file ``mtl``)."""
    name: str
    faces: list
    material: str | None = None
    kd: tuple | None = None
    mtl: Path | None = None


def _index(token: str, count: int) -> int:
    i = int(token.split("/")[0])
    return i - 1 if i > 0 else count + i


def read_mtl_kd(path: Path) -> dict:
    """{material name: Kd (r, g, b)} of an MTL file (materials without Kd are left out)."""
    out, current = {}, None
    for line in path.read_text(errors="replace").splitlines():
        words = line.split()
        if not words:
            continue
        if words[0] == "newmtl" and len(words) > 1:
            current = " ".join(words[1:])
        elif words[0] == "Kd" and current is not None and len(words) >= 4:
            out[current] = tuple(float(w) for w in words[1:4])
    return out


def read_obj(path: Path):
    """(positions (n, 3) float64, [ObjPart, ...] in file order) of an OBJ file."""
    positions, parts, order = [], {}, []
    name, material, libs = "default", None, []
    for lineno, line in enumerate(Path(path).read_text(errors="replace").splitlines(), 1):
        words = line.split("#", 1)[0].split()
        if not words:
            continue
        key = words[0]
        try:
            if key == "v":
                positions.append([float(w) for w in words[1:4]])
            elif key in ("o", "g"):
                name = " ".join(words[1:]) or "default"
            elif key == "usemtl":
                material = " ".join(words[1:]) or None
            elif key == "mtllib":
                libs.extend(words[1:])
            elif key == "f":
                idx = [_index(w, len(positions)) for w in words[1:]]
                if name not in parts:
                    parts[name] = ObjPart(name, [], material)
                    order.append(name)
                parts[name].faces.extend([idx[0], idx[k], idx[k + 1]] for k in range(1, len(idx) - 1))
        except (ValueError, IndexError):
            raise ValueError(f"line {lineno}: cannot read '{line.strip()[:40]}'") from None
    kd = {}
    for lib in libs:
        mtl = Path(path).parent / lib
        if mtl.is_file():
            kd.update({name: (value, mtl) for name, value in read_mtl_kd(mtl).items()})
    for p in parts.values():
        p.kd, p.mtl = kd.get(p.material, (None, None)) if p.material else (None, None)
    return np.asarray(positions, float).reshape(-1, 3), [parts[n] for n in order]


def part_mesh(V, part: ObjPart):
    """(V, F) of one part with only the vertices its faces use."""
    F = np.asarray(part.faces, np.int64).reshape(-1, 3)
    if len(F) and (F.min() < 0 or F.max() >= len(V)):
        raise ValueError(f"part '{part.name}' has face indices outside 1..{len(V)}")
    used, F = np.unique(F, return_inverse=True)
    return V[used], F.reshape(-1, 3)


def read_part(path: Path, name: str):
    """(V, F) of the part ``name`` of an OBJ file; ValueError naming the parts if there is none."""
    V, parts = read_obj(path)
    for p in parts:
        if p.name == name:
            return part_mesh(V, p)
    raise KeyError(f"no part '{name}' in {Path(path).name} (parts: {', '.join(p.name for p in parts) or 'none'})")


def object_name(obj: str, part: str) -> str:
    """Scene-object name of a part: ``<object>_<part>`` with characters other than letters,
    digits, ``-`` and ``_`` replaced by ``_`` (Mitsuba ids may not contain ``.``)."""
    return f"{obj}_{re.sub(r'[^A-Za-z0-9_-]', '_', part)}"


def _mtl_bsdf(part: ObjPart) -> BsdfConfig:
    """A diffuse BSDF of the part's Kd, which must be a reflectance: finite, in [0, 1]."""
    kd = tuple(float(c) for c in part.kd)
    if not all(0.0 <= c <= 1.0 for c in kd):
        raise ConfigError(part.mtl, f"material '{part.material}'", f"Kd: expected 3 numbers in [0, 1] "
                          f"(a diffuse reflectance), got {' '.join(f'{c:g}' for c in kd)}")
    return BsdfConfig("diffuse", {"reflectance": kd})


def expand_objects(scene: SceneConfig, file: str) -> SceneConfig:
    """The scene with each ``split: true`` object replaced by one object per OBJ part, and
    objects without a ``bsdf`` whose part has an MTL ``Kd`` given a diffuse BSDF of that colour.
    Per-part ``parts: {NAME: {bsdf, edges, smooth}}`` entries override the object's keys."""
    out = []
    for obj in scene.objects:
        spec = obj.mesh
        if spec.file is None or (not spec.split and spec.part is None):
            out.append(obj)
            continue
        where = Where(file, spec.key)
        if not spec.file.is_file():
            raise where.fail(f"mesh file not found: {spec.file}")
        try:
            _, parts = read_obj(spec.file)
        except (OSError, ValueError) as exc:
            raise where.fail(f"cannot read mesh {spec.file.name}: {exc}") from None
        if not spec.split:
            part = next((p for p in parts if p.name == spec.part), None)
            if part is not None and not obj.bsdf_given and part.kd is not None:
                obj = replace(obj, bsdf=_mtl_bsdf(part))
            out.append(replace(obj, bsdf_given=True))
            continue
        unknown = [n for n in obj.parts if n not in {p.name for p in parts}]
        if unknown:
            raise Where(file, f"{obj.key}.parts.{unknown[0]}").fail(
                f"no part '{unknown[0]}' in {spec.file.name} (parts: {', '.join(p.name for p in parts) or 'none'})")
        if not parts:
            raise where.fail(f"{spec.file.name} has no faces")
        for p in parts:
            over = obj.parts.get(p.name, {})
            bsdf = over.get("bsdf") or (obj.bsdf if obj.bsdf_given or p.kd is None else _mtl_bsdf(p))
            out.append(replace(obj, name=object_name(obj.name, p.name), bsdf=bsdf, parts={}, bsdf_given=True,
                               mesh=replace(spec, split=False, part=p.name),
                               edges=over.get("edges", obj.edges), smooth=over.get("smooth", obj.smooth)))
    return replace(scene, objects=out)
