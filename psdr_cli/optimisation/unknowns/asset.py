"""What ``psdr export`` writes of a reconstruction (:class:`Asset`), filled by the command from the
mesh and by each unknown from what the run recovered (:meth:`Unknown.export`), and the
experiment's own object colour where no albedo was recovered. Reads the experiment; writes
nothing (:mod:`psdr_cli.commands.export` writes the files)."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

#: The grey of an object with no colour of its own.
GREY = (0.5, 0.5, 0.5)

#: The MTL's PBR maps of recovered material textures (linear grey PNGs): map_Pr, map_Pm.
PBR_PNG = {"roughness": "roughness.png", "metallic": "metallic.png"}


@dataclass
class Asset:
    """What is exported: the mesh in the user's coordinates, its UVs (Mitsuba's convention) and
    diffuse albedo (a linear (H, W, 3) texture or an RGB colour), and the environment."""
    V: np.ndarray
    F: np.ndarray
    uv: np.ndarray | None = None
    texture: np.ndarray | None = None
    color: tuple = GREY
    environment: np.ndarray | None = None
    metallic: float = 0.0
    roughness: float = 1.0
    maps: dict = field(default_factory=dict)  # "roughness"/"metallic" → (H, W) glTF-convention texels
    notes: list = field(default_factory=list)
    record: dict = field(default_factory=dict)


def run_object(exp):
    """The run's optimised object (its scene entry), or None without an experiment."""
    name = exp.optimize.object if exp is not None and exp.optimize else None
    return next((o for o in exp.scene.objects if o.name == name), None) if name else None


def object_color(exp, notes: list) -> tuple:
    """The constant diffuse reflectance (or base colour) of the run's object, else grey."""
    obj = run_object(exp)
    if obj is not None:
        value = obj.bsdf.params.get("reflectance", obj.bsdf.params.get("base_color"))
        if isinstance(value, (int, float)):
            return (float(value),) * 3
        if isinstance(value, tuple) and len(value) == 3:
            return tuple(float(v) for v in value)
        notes.append("the run recovered no albedo and its object has no constant colour: exported grey")
    return GREY
