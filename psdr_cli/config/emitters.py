"""``scene.emitters``: area lights, environment maps, skies and constant environments."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from .limits import MAX_RADIANCE
from .values import Parser, Section, choice, color, number, path_relative_to, unit, vector
from .vocabularies import EMITTER_TYPES


@dataclass
class EmitterConfig:
    type: str  # area | envmap | sky | constant
    key: str   # key path in the file, for error messages
    radiance: tuple = (1.0, 1.0, 1.0)
    center: tuple = (0.0, 0.0, 0.0)
    normal: tuple = (0.0, 0.0, -1.0)
    size: tuple = (1.0, 1.0)
    file: Path | None = None
    scale: float = 1.0
    rotate_deg: float = 0.0
    sun_direction: tuple = (0.0, 0.0, 1.0)
    turbidity: float = 3.0
    albedo: float = 0.3
    sun_scale: float = 1.0
    sky_scale: float = 1.0
    up: tuple = (0.0, 0.0, 1.0)  # not a YAML key: the world's up that an envmap's zenith turns to (a dataset's)


def parse_emitter(base: Path) -> Parser:
    def parse(value, where):
        sec = Section(value, where)
        kind = sec.get("type", choice(*EMITTER_TYPES))
        em = EmitterConfig(type=kind, key=where.path)
        if kind == "area":
            em.center = sec.get("center", vector(3))
            em.normal = unit(sec.get("normal", vector(3, nonzero=True)))
            em.size = sec.get("size", vector(2, positive=True))
            em.radiance = sec.get("radiance", color)
        elif kind == "envmap":
            em.file = sec.get("file", path_relative_to(base))
            em.scale = sec.get("scale", number(minimum=0, maximum=MAX_RADIANCE), 1.0)
            em.rotate_deg = sec.get("rotate_deg", number(), 0.0)
        elif kind == "sky":
            em.sun_direction = unit(sec.get("sun_direction", vector(3, nonzero=True)))
            em.turbidity = sec.get("turbidity", number(minimum=1, maximum=10), 3.0)
            em.albedo = sec.get("albedo", number(minimum=0, maximum=1), 0.3)
            em.sun_scale = sec.get("sun_scale", number(minimum=0, maximum=MAX_RADIANCE), 1.0)
            em.sky_scale = sec.get("sky_scale", number(minimum=0, maximum=MAX_RADIANCE), 1.0)
            em.rotate_deg = sec.get("rotate_deg", number(), 0.0)
        else:
            em.radiance = sec.get("radiance", color)
        sec.done()
        return em
    return parse
