"""The unknowns of an optimisation besides the shape: ``optimize.envmap`` (the environment map
itself), ``optimize.material`` (scalar BSDF parameters) and ``optimize.cameras`` (pose
corrections of the training views)."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from .limits import MAX_FILM
from .values import Parser, Section, boolean, choice, color, describe, integer, number
from .vocabularies import CAMERA_MODES, ENVMAP_MEANS


@dataclass
class EnvmapUnknown:
    """``optimize.envmap``: the scene's ``envmap`` emitter's lat-long map as an unknown, optimised
    as log-radiance x (the map is scale · exp(x), positive by construction)."""
    resolution: tuple = (32, 16)           # (W, H) texels of the lat-long map
    init: tuple | None = None              # constant radiance (r, g, b); None: the scene map's mean
    init_file: Path | None = None          # an EXR lat-long map, resampled to the resolution
    learning_rate: float = 0.05            # Adam step on the log-radiance
    smoothness: float = 0.0                # weight of the Laplacian prior on the log-radiance
    mean: str = "auto"                     # fixed | free | auto (fixed when optimize.albedo is set)


#: ``optimize.material`` unknowns: (clamp range, {BSDF type: Mitsuba parameter}).
MATERIAL_UNKNOWNS = {
    "roughness": ((0.01, 1.0), {"principled": "roughness", "roughconductor": "alpha", "roughdielectric": "alpha"}),
    "metallic": ((0.0, 1.0), {"principled": "metallic"}),
    "specular": ((0.0, 1.0), {"principled": "specular"}),
}

#: Mitsuba's defaults of those parameters (a texture starts from them when neither
#: ``optimize.material.NAME.init`` nor the BSDF gives a value).
MATERIAL_DEFAULTS = {"roughness": 0.5, "alpha": 0.1, "metallic": 0.0, "specular": 0.5}


@dataclass
class MaterialUnknown:
    """One scalar BSDF parameter of ``optimize.material`` (:data:`MATERIAL_UNKNOWNS`)."""
    name: str
    init: float | None = None              # default: the object's BSDF value
    learning_rate: float = 0.02
    texture: tuple | None = None           # (W, H): a one-channel bitmap instead of one value


def parse_envmap_unknown(base: Path) -> Parser:
    """``optimize.envmap: {resolution: [W, H], init: VALUE | [r, g, b] | FILE.exr, learning_rate,
    smoothness, mean}``; an init file's texels are checked once the experiment is loaded
    (:func:`psdr_cli.experiment.load.check_envmap_init`: OpenEXR is not imported here)."""
    def init_value(value, where):
        if isinstance(value, str):
            path = Path(value) if Path(value).is_absolute() else base / value
            if path.suffix.lower() != ".exr":
                raise where.fail(f"expected a radiance value, [r, g, b] or an EXR file, got {describe(value)}")
            if not path.is_file():
                raise where.fail(f"file not found: {path}")
            return path
        return color(value, where)

    def parse(value, where) -> EnvmapUnknown:
        sec = Section(value, where)
        e = EnvmapUnknown()
        e.resolution = sec.get("resolution", _envmap_size, e.resolution)
        init = sec.get("init", init_value, None)
        if isinstance(init, Path):
            e.init_file = init
        elif init is not None:
            if max(init) <= 0:
                raise where.child("init").fail(f"expected a radiance > 0 (the map is optimised as its "
                                               f"logarithm), got {describe(list(init))}")
            e.init = init
        e.learning_rate = sec.get("learning_rate", number(positive=True), e.learning_rate)
        e.smoothness = sec.get("smoothness", number(minimum=0), e.smoothness)
        e.mean = sec.get("mean", choice(*ENVMAP_MEANS), e.mean)
        sec.done()
        return e
    return parse


def _envmap_size(value, where):
    """[W, H] of an environment map being optimised: W in 2..4096, H in 2..2048."""
    if not isinstance(value, list) or len(value) != 2:
        raise where.fail(f"expected [width, height], got {describe(value)}")
    return (integer(2, 4096)(value[0], where.child(0)), integer(2, 2048)(value[1], where.child(1)))


def texture_size(value, where):
    """[W, H] of a texture being optimised: integers in 1..MAX_FILM."""
    if not isinstance(value, list) or len(value) != 2:
        raise where.fail(f"expected [width, height], got {describe(value)}")
    return tuple(integer(1, MAX_FILM)(v, where.child(i)) for i, v in enumerate(value))


def parse_material(value, where) -> tuple:
    """``optimize.material: {roughness: {init, learning_rate, texture}, metallic: ..., specular: ...}``."""
    sec = Section(value, where)
    out = []
    for name, ((lo, hi), _) in MATERIAL_UNKNOWNS.items():
        if not sec.has(name):
            sec.used.add(name)
            continue
        w = where.child(name)
        m = Section(sec.get(name, lambda v, _: v), w)
        u = MaterialUnknown(name, init=m.get("init", number(minimum=lo, maximum=hi), None),
                            learning_rate=m.get("learning_rate", number(positive=True), 0.02),
                            texture=m.get("texture", texture_size, None))
        m.done()
        out.append(u)
    sec.done()
    if not out:
        raise where.fail(f"expected at least one of {', '.join(MATERIAL_UNKNOWNS)}")
    return tuple(out)


@dataclass
class CamerasUnknown:
    """``optimize.cameras``: a pose correction per training view (a rotation about the camera's
    centre and a translation in units of its distance to the object), refined with the shape
    (:mod:`psdr_cli.optimisation.camera_refinement`). ``mode``: ``auto`` (on for camera datasets), ``on`` (a
    mapping was given) or ``off``."""
    mode: str = "auto"
    rotation: bool = True                  # refine the orientations
    translation: bool = True               # refine the positions
    learning_rate: float = 2e-3            # Adam step: radians, and camera distances
    learning_rate_final: float = 2e-4      # the step at the run's last iteration (a linear fall)
    start: int | None = None               # first refined iteration (None: a fifth of the run)
    warmup: int = 20                       # iterations over which the step ramps up from 0
    max_rotation_deg: float = 3.0          # a view whose correction goes beyond stops (runaway)
    max_translation: float = 0.05          # the same for the translation (camera distances)
    focal: bool = False                    # refine the focal length, one scale per camera model
    focal_learning_rate: float = 2e-3      # Adam step of log s (focal_refinement.py)
    max_focal: float = 0.1                 # a model whose |log s| passes log(1 + max_focal) stops


def parse_cameras(value, where) -> CamerasUnknown:
    """``optimize.cameras: auto | on | off | {rotation, translation, focal, learning_rate,
    focal_learning_rate, start, warmup, max_rotation_deg, max_translation, max_focal}`` (a mapping
    turns refinement on)."""
    if isinstance(value, bool):
        return CamerasUnknown(mode="on" if value else "off")
    if isinstance(value, str):
        return CamerasUnknown(mode=choice(*CAMERA_MODES)(value, where))
    sec = Section(value, where)
    c = CamerasUnknown(mode="on")
    c.rotation = sec.get("rotation", boolean, c.rotation)
    c.translation = sec.get("translation", boolean, c.translation)
    c.learning_rate = sec.get("learning_rate", number(positive=True, maximum=0.1), c.learning_rate)
    c.learning_rate_final = sec.get("learning_rate_final", number(minimum=0, maximum=0.1), c.learning_rate / 10)
    c.start = sec.get("start", integer(0), c.start)
    c.warmup = sec.get("warmup", integer(0), c.warmup)
    c.max_rotation_deg = sec.get("max_rotation_deg", number(positive=True, maximum=45), c.max_rotation_deg)
    c.max_translation = sec.get("max_translation", number(positive=True, maximum=1), c.max_translation)
    c.focal = sec.get("focal", boolean, c.focal)
    c.focal_learning_rate = sec.get("focal_learning_rate", number(positive=True, maximum=0.1), c.focal_learning_rate)
    c.max_focal = sec.get("max_focal", number(positive=True, maximum=0.5), c.max_focal)
    sec.done()
    if not (c.rotation or c.translation):
        raise where.fail("expected rotation or translation (or both) to be refined (or cameras: off)")
    return c
