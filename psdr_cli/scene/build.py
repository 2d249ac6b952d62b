"""Mitsuba scenes from experiment configurations.

World convention: z is up (as in Blender). Cameras are Mitsuba ``perspective`` sensors with a
horizontal field of view and a box pixel filter; objects are ``mi.Mesh`` instances built from
numpy arrays, so their ``<name>.vertex_positions`` are differentiable scene parameters.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import mitsuba as mi
import numpy as np

from . import mitsuba_xml
from ..config.emitters import EmitterConfig
from ..config.experiment_file import Experiment
from ..config.limits import MAX_TEXELS
from ..config.objects import BSDF_RANGES, BitmapConfig, ObjectConfig
from ..config.scene_section import SceneConfig
from ..config.scene_ids import INTEGRATOR_ID, emitter_id, sensor_id
from ..errors import ConfigError
from ..support import fileio
from .meshes import ObjectMesh, build_objects, has_bitmap


@dataclass
class Scene:
    """A loaded Mitsuba scene together with what psdr needs to know about it."""
    mi_scene: object
    config: SceneConfig
    objects: dict = field(default_factory=dict)  # name -> ObjectMesh

    @property
    def sensors(self):
        return self.mi_scene.sensors()

    @property
    def resolution(self):
        return self.config.width, self.config.height


def _rgb(value):
    return {"type": "rgb", "value": list(value)}


def read_bitmap(b: BitmapConfig, name: str, file: str, key: str):
    """``mi.Bitmap`` of a bitmap value, its texels checked: finite, and within the parameter's
    physical range (``config.BSDF_RANGES``, e.g. [0, 1] for a reflectance) once converted to linear
    values as Mitsuba uses them (sRGB-decoded unless ``raw``). An in-memory ``data`` image is
    linear float RGB."""
    if b.data is not None:
        bitmap = mi.Bitmap(np.ascontiguousarray(b.data, np.float32))
    else:
        check_image_size(b.file, file, key + ".file", "texture")
        try:
            bitmap = mi.Bitmap(exr_texels(b.file)) if b.file.suffix.lower() == ".exr" else mi.Bitmap(str(b.file))
        except Exception as exc:  # noqa: BLE001 - a damaged or unsupported image
            raise ConfigError(file, key + ".file", f"cannot read texture {b.file.name}: "
                              f"{str(exc).splitlines()[0] if str(exc) else type(exc).__name__}") from None
    texels = np.asarray(bitmap.convert(component_format=mi.Struct.Type.Float32,
                                       srgb_gamma=False if not b.raw else bitmap.srgb_gamma()), np.float64)
    what = b.file.name if b.file is not None else "texture"
    if texels.size == 0:
        raise ConfigError(file, key + ".file", f"texture {what} is empty")
    if not np.isfinite(texels).all():
        raise ConfigError(file, key + ".file", f"texture {what} has {int((~np.isfinite(texels)).sum())} "
                          f"NaN or infinite values")
    lo, hi = BSDF_RANGES.get(name, (-float("inf"), float("inf")))
    if texels.min() < lo or texels.max() > hi:
        raise ConfigError(file, key + ".file", f"texture {what} has values in [{texels.min():g}, "
                          f"{texels.max():g}], expected [{lo:g}, {hi:g}] for {name}")
    return bitmap


def check_image_size(path, file: str, key: str, what: str):
    """Refuse an image file of more than :data:`MAX_TEXELS` texels from its header, before it is
    decoded (and converted to floats, several bytes per texel)."""
    problem = fileio.image_too_large(path, MAX_TEXELS)
    if problem:
        raise ConfigError(file, key, f"{what} {problem}")


def exr_texels(path) -> np.ndarray:
    """(H, W, 3) or (H, W, 1) float32 texels of an EXR texture (R, G, B or Y; alpha dropped), read
    with :mod:`fileio` (``mi.Bitmap`` reading an EXR hangs while Dr.Jit runs one thread, as
    ``psdr optimize`` does)."""
    channels = fileio.read_exr(path)
    if all(c in channels for c in "RGB"):
        return np.ascontiguousarray(np.stack([channels[c] for c in "RGB"], -1), np.float32)
    if "Y" in channels:
        return np.ascontiguousarray(channels["Y"][..., None], np.float32)
    names = ", ".join(sorted(k for k in channels if k != "__header__"))
    raise ValueError(f"no R, G, B or Y channels (has {names or 'none'})")


def bsdf_dict(obj: ObjectConfig, file: str = "") -> dict:
    """Mitsuba BSDF dictionary; RGB triples become ``rgb`` textures, bitmaps Mitsuba ``bitmap``
    textures (read and checked by :func:`read_bitmap`), names pass through."""
    d = {"type": obj.bsdf.type}
    for name, value in obj.bsdf.params.items():
        if isinstance(value, BitmapConfig):
            d[name] = {"type": "bitmap", "bitmap": read_bitmap(value, name, file, f"{obj.key}.bsdf.{name}"),
                       "filter_type": value.filter_type, "wrap_mode": value.wrap_mode, "raw": value.raw}
        else:
            d[name] = _rgb(value) if isinstance(value, tuple) else value
    return d


def mitsuba_mesh(name: str, V, F, bsdf: dict, smooth: bool = False, uv=None):
    """``mi.Mesh`` with the given triangles; flat-shaded unless ``smooth``; with per-vertex texture
    coordinates ``uv`` (n, 2) when given (:func:`psdr_cli.scene.mitsuba_xml.mesh` with this BSDF)."""
    return mitsuba_xml.mesh(name, V, F, mi.load_dict(bsdf), texcoords=uv, smooth=smooth)


def look_at(origin, target, up):
    return mi.ScalarTransform4f().look_at(origin=list(origin), target=list(target), up=list(up))


def sensor_dict(cam, width: int, height: int) -> dict:
    """Mitsuba ``perspective`` sensor of a :class:`CameraConfig`; its principal point offset (in
    Mitsuba's convention, see ``CameraConfig.principal_point``) only when it is not centred."""
    d = {
        "type": "perspective",
        "fov": cam.fov,
        "fov_axis": "x",
        "to_world": look_at(cam.origin, cam.target, cam.up),
        "film": {"type": "hdrfilm", "width": width, "height": height, "pixel_format": "rgb",
                 "rfilter": {"type": "box"}},
        "sampler": {"type": "independent"},
    }
    ox, oy = cam.principal_point
    if ox or oy:
        d["principal_point_offset_x"], d["principal_point_offset_y"] = float(ox), float(oy)
    return d


def rectangle_frame(center, normal, size) -> np.ndarray:
    """to_world of Mitsuba's ``rectangle`` ([-1,1]² at z = 0, normal +z) for an area light.

    The width axis is n × z (or x for lights facing up or down), the height axis n × width.
    """
    n = np.asarray(normal, float)
    ref = np.array([0.0, 0.0, 1.0]) if abs(n[2]) < 0.999 else np.array([0.0, -1.0, 0.0])
    t = np.cross(n, ref)
    t /= np.linalg.norm(t)
    b = np.cross(n, t)
    M = np.eye(4)
    M[:3, 0] = t * size[0] / 2
    M[:3, 1] = b * size[1] / 2
    M[:3, 2] = n
    M[:3, 3] = center
    return M


def environment_to_world(rotate_deg: float, up=(0.0, 0.0, 1.0)):
    """Lat-long maps are y-up in Mitsuba: turn +y to +z, rotate about z by ``rotate_deg``, then
    turn +z to the world's ``up`` (the shortest rotation; none for z-up worlds)."""
    turned = mi.ScalarTransform4f().rotate([0, 0, 1], rotate_deg).rotate([1, 0, 0], 90)
    up = np.asarray(up, np.float64) / np.linalg.norm(up)
    if np.allclose(up, (0.0, 0.0, 1.0)):
        return turned
    axis = np.cross((0.0, 0.0, 1.0), up)
    if np.linalg.norm(axis) < 1e-9:  # up = −z
        axis = np.array([1.0, 0.0, 0.0])
    angle = float(np.degrees(np.arccos(np.clip(up[2], -1.0, 1.0))))
    return mi.ScalarTransform4f().rotate(list(axis / np.linalg.norm(axis)), angle) @ turned


def emitter_dict(em: EmitterConfig, file: str) -> dict:
    if em.type == "area":
        return {"type": "rectangle", "to_world": mi.ScalarTransform4f(rectangle_frame(em.center, em.normal, em.size)),
                "emitter": {"type": "area", "radiance": _rgb(em.radiance)},
                "bsdf": {"type": "diffuse", "reflectance": _rgb((0.0, 0.0, 0.0))}}
    if em.type == "envmap" and em.file is None:  # the unknown map of a capture without a probe
        texels = np.broadcast_to(np.asarray(em.radiance, np.float32), (8, 16, 3))
        return {"type": "envmap", "bitmap": mi.Bitmap(np.ascontiguousarray(texels)), "scale": em.scale,
                "to_world": environment_to_world(em.rotate_deg, em.up)}
    if em.type == "envmap":
        if not em.file.exists():
            raise ConfigError(file, em.key + ".file", f"environment map not found: {em.file}")
        check_image_size(em.file, file, em.key + ".file", "environment map")
        try:
            bitmap = mi.Bitmap(exr_texels(em.file)) if em.file.suffix.lower() == ".exr" else mi.Bitmap(str(em.file))
        except Exception as exc:  # noqa: BLE001
            raise ConfigError(file, em.key + ".file", f"cannot read environment map: {str(exc).splitlines()[0]}") from None
        texels = np.asarray(bitmap)
        if texels.dtype.kind == "f" and not np.isfinite(texels).all():
            raise ConfigError(file, em.key + ".file", f"environment map {em.file.name} has "
                              f"{int((~np.isfinite(texels)).sum())} NaN or infinite values")
        return {"type": "envmap", "bitmap": bitmap, "scale": em.scale, "to_world": environment_to_world(em.rotate_deg, em.up)}
    if em.type == "sky":
        return {"type": "sunsky", "sun_direction": list(em.sun_direction), "turbidity": em.turbidity,
                "albedo": em.albedo, "sun_scale": em.sun_scale, "sky_scale": em.sky_scale,
                "to_world": mi.ScalarTransform4f().rotate([0, 0, 1], em.rotate_deg)}
    return {"type": "constant", "radiance": _rgb(em.radiance)}


def build_scene(exp: Experiment, objects: dict | None = None, cameras: list | None = None) -> Scene:
    """Mitsuba scene of an experiment: every camera, emitter and object.

    ``objects`` may override meshes by name (``{name: (V, F)}`` or ``(V, F, UV)``, e.g. the
    current shape of an optimisation; a (V, F) override keeps the object's UVs when F is the
    object's own triangle list, i.e. the same vertices moved); ``cameras`` may replace the camera
    list. An object whose BSDF has a bitmap texture must have UVs. ``exp`` is as loaded
    (:mod:`psdr_cli.experiment.load`): an XML scene read, split OBJ objects expanded into their parts;
    only its ``scene`` and ``file`` are read (an optimisation's problem passes just those:
    :class:`psdr_cli.optimisation.problem.SceneSource`).
    """
    if exp.scene.mitsuba is not None:
        return build_xml_scene(exp, objects or {}, cameras)
    cfg = exp.scene
    built = build_objects(exp)
    for name, mesh in (objects or {}).items():
        V, F = np.asarray(mesh[0], float), np.asarray(mesh[1], np.int64)
        old = built[name]
        uv = mesh[2] if len(mesh) > 2 else (old.uv if old.faces.shape == F.shape and (old.faces == F).all() else None)
        built[name] = ObjectMesh(name, V, F, old.edges, old.config, uv)
    d = {"type": "scene", INTEGRATOR_ID: {"type": "path", "max_depth": cfg.max_depth}}
    for i, cam in enumerate(cameras or cfg.cameras):
        d[sensor_id(i)] = sensor_dict(cam, cfg.width, cfg.height)
    for i, em in enumerate(cfg.emitters):
        d[emitter_id(i)] = emitter_dict(em, str(exp.file))
    for name, om in built.items():
        if om.uv is None and has_bitmap(om.config):
            raise ConfigError(exp.file, om.config.key + ".bsdf", "a bitmap texture needs a mesh with UV "
                              "coordinates (an OBJ with 'vt', a PLY with s/t, a plane, or 'shape: sphere, uv: true')")
        try:
            bsdf = bsdf_dict(om.config, str(exp.file))
            d[name] = mitsuba_mesh(name, om.vertices, om.faces, bsdf, om.config.smooth, om.uv)
        except ConfigError:
            raise
        except Exception as exc:  # noqa: BLE001 - Mitsuba rejects a BSDF parameter value
            raise ConfigError(exp.file, om.config.key + ".bsdf",
                              f"Mitsuba rejected the BSDF: {str(exc).splitlines()[0]}") from None
    try:
        mi_scene = mi.load_dict(d)
    except Exception as exc:  # noqa: BLE001 - Mitsuba rejects a parameter value
        raise ConfigError(exp.file, "scene", f"Mitsuba could not build the scene: {str(exc).splitlines()[0]}") from None
    return Scene(mi_scene, cfg, built)


def build_xml_scene(exp: Experiment, objects: dict, cameras: list | None) -> Scene:
    """The Mitsuba scene of a loaded XML experiment (see :mod:`psdr_cli.scene.mitsuba_xml`)."""
    cfg = exp.scene
    unknown = [name for name in objects if name not in {o.name for o in cfg.objects}]
    if unknown:
        raise ConfigError(exp.file, "scene", f"no object '{unknown[0]}' in {cfg.mitsuba.file.name}")
    sensors = None
    if cameras or cfg.mitsuba.cameras_given:
        sensors = [sensor_dict(cam, cfg.width, cfg.height) for cam in (cameras or cfg.cameras)]
    entries, geometry = mitsuba_xml.scene_entries(exp, objects, sensors)
    d = {"type": "scene", INTEGRATOR_ID: {"type": "path", "max_depth": cfg.max_depth}, **entries}
    try:
        mi_scene = mi.load_dict(d)
    except Exception as exc:  # noqa: BLE001
        raise ConfigError(cfg.mitsuba.file, "", f"Mitsuba could not rebuild the scene: {str(exc).splitlines()[0]}") from None
    built = {o.name: ObjectMesh(o.name, *geometry[o.name], o.edges, o) for o in cfg.objects}
    return Scene(mi_scene, cfg, built)
