"""``parameter``: the scalar θ of ``psdr grad`` (an object or camera moved, rotated or scaled,
a camera's focal length scaled, or the environment rotated)."""
from __future__ import annotations

from dataclasses import dataclass

from .values import Section, choice, integer, string, unit, vector
from .vocabularies import PARAMETER_KINDS


@dataclass
class ParameterConfig:
    kind: str  # translate | rotate | scale | envmap_rotate | focal (a camera's: θ = log s)
    object: str | None = None
    axis: tuple = (1.0, 0.0, 0.0)
    camera: int | None = None  # translate/rotate this camera (view index), or scale its focal length


DEFAULT_AXIS = {"translate": (1.0, 0.0, 0.0), "rotate": (0.0, 0.0, 1.0), "scale": (1.0, 1.0, 1.0),
                "envmap_rotate": (0.0, 0.0, 1.0), "focal": (1.0, 0.0, 0.0)}


def parse_parameter(value, where, up=(0.0, 0.0, 1.0)) -> ParameterConfig:
    """The ``parameter:`` section; rotations default to the axis ``up`` (the scene's up axis)."""
    sec = Section(value, where)
    kind = sec.get("kind", choice(*PARAMETER_KINDS))
    obj = sec.get("object", string, None)
    camera = sec.get("camera", integer(0), None)
    if camera is not None and obj is not None:
        raise where.child("camera").fail("give either 'object' or 'camera', not both")
    if camera is not None and kind not in ("translate", "rotate", "focal"):
        raise where.child("camera").fail(f"a camera can only be translated or rotated, or its focal length "
                                         f"scaled (kind 'focal'), not '{kind}'")
    if kind == "focal" and camera is None:
        raise where.child("camera").fail("missing (kind 'focal' scales a camera's focal length: 'camera: INDEX')")
    if kind == "focal" and sec.has("axis"):
        raise where.child("axis").fail("not allowed for kind 'focal' (θ = log s scales the focal length)")
    if kind != "envmap_rotate" and obj is None and camera is None:
        raise where.child("object").fail(f"missing (required for kind '{kind}'; or 'camera: INDEX')")
    if kind == "envmap_rotate" and obj is not None:
        raise where.child("object").fail("not allowed for kind 'envmap_rotate'")
    default = tuple(up) if kind in ("rotate", "envmap_rotate") else DEFAULT_AXIS[kind]
    axis = sec.get("axis", vector(3, nonzero=True), default)
    sec.done()
    return ParameterConfig(kind=kind, object=obj, axis=axis if kind == "scale" else unit(axis), camera=camera)
