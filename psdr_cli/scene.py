"""Mitsuba scenes from experiment configurations.

World convention: z is up (as in Blender). Cameras are Mitsuba ``perspective`` sensors with a
horizontal field of view and a box pixel filter; objects are ``mi.Mesh`` instances built from
numpy arrays, so their ``<name>.vertex_positions`` are differentiable scene parameters.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import mitsuba as mi
import numpy as np

from . import meshes, mitsuba_scene
from .config import EmitterConfig, Experiment, ObjectConfig, SceneConfig
from .errors import ConfigError


@dataclass
class ObjectMesh:
    """World-space geometry of one scene object as built (before any optimisation)."""
    name: str
    vertices: np.ndarray
    faces: np.ndarray
    edges: bool
    config: ObjectConfig


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


def bsdf_dict(obj: ObjectConfig) -> dict:
    """Mitsuba BSDF dictionary; RGB triples become ``rgb`` textures, names pass through."""
    d = {"type": obj.bsdf.type}
    for name, value in obj.bsdf.params.items():
        d[name] = _rgb(value) if isinstance(value, tuple) else value
    return d


def object_mesh(obj: ObjectConfig, file: str):
    """World-space (V, F) of an object: its mesh, validated, then its transform (an XML scene's
    mesh: as Mitsuba loaded it, in world space)."""
    if obj.mesh.shape == "mitsuba":
        return mitsuba_scene.object_geometry(obj)
    V, F = meshes.load_mesh(obj.mesh, file)
    V = meshes.apply_transform(V, meshes.transform_matrix(obj.transform))
    return V, F


def mitsuba_mesh(name: str, V, F, bsdf: dict, smooth: bool = False):
    """``mi.Mesh`` with the given triangles; flat-shaded unless ``smooth``."""
    props = mi.Properties()
    props["bsdf"] = mi.load_dict(bsdf)
    mesh = mi.Mesh(name, len(V), len(F), props, smooth)
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(np.ascontiguousarray(V, np.float32).ravel())
    params["faces"] = mi.UInt32(np.ascontiguousarray(F, np.uint32).ravel())
    params.update()
    return mesh


def look_at(origin, target, up):
    return mi.ScalarTransform4f().look_at(origin=list(origin), target=list(target), up=list(up))


def sensor_dict(cam, width: int, height: int) -> dict:
    return {
        "type": "perspective",
        "fov": cam.fov,
        "fov_axis": "x",
        "to_world": look_at(cam.origin, cam.target, cam.up),
        "film": {"type": "hdrfilm", "width": width, "height": height, "pixel_format": "rgb",
                 "rfilter": {"type": "box"}},
        "sampler": {"type": "independent"},
    }


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


def environment_to_world(rotate_deg: float):
    """Lat-long maps are y-up in Mitsuba: turn +y to +z, then rotate about z by ``rotate_deg``."""
    return mi.ScalarTransform4f().rotate([0, 0, 1], rotate_deg).rotate([1, 0, 0], 90)


def emitter_dict(em: EmitterConfig, file: str) -> dict:
    if em.type == "area":
        return {"type": "rectangle", "to_world": mi.ScalarTransform4f(rectangle_frame(em.center, em.normal, em.size)),
                "emitter": {"type": "area", "radiance": _rgb(em.radiance)},
                "bsdf": {"type": "diffuse", "reflectance": _rgb((0.0, 0.0, 0.0))}}
    if em.type == "envmap":
        if not em.file.exists():
            raise ConfigError(file, em.key + ".file", f"environment map not found: {em.file}")
        try:
            bitmap = mi.Bitmap(str(em.file))
        except Exception as exc:  # noqa: BLE001
            raise ConfigError(file, em.key + ".file", f"cannot read environment map: {str(exc).splitlines()[0]}") from None
        return {"type": "envmap", "bitmap": bitmap, "scale": em.scale, "to_world": environment_to_world(em.rotate_deg)}
    if em.type == "sky":
        return {"type": "sunsky", "sun_direction": list(em.sun_direction), "turbidity": em.turbidity,
                "albedo": em.albedo, "sun_scale": em.sun_scale, "sky_scale": em.sky_scale,
                "to_world": mi.ScalarTransform4f().rotate([0, 0, 1], em.rotate_deg)}
    return {"type": "constant", "radiance": _rgb(em.radiance)}


def build_objects(exp: Experiment) -> dict:
    """World-space meshes of every object, validated (no Mitsuba needed)."""
    out = {}
    for obj in exp.scene.objects:
        V, F = object_mesh(obj, str(exp.file))
        out[obj.name] = ObjectMesh(obj.name, V, F, obj.edges, obj)
    return out


def build_scene(exp: Experiment, objects: dict | None = None, cameras: list | None = None) -> Scene:
    """Mitsuba scene of an experiment: every camera, emitter and object.

    ``objects`` may override meshes by name (``{name: (V, F)}``, e.g. the current shape of an
    optimisation); ``cameras`` may replace the camera list. An XML scene (``scene.mitsuba``) is
    read by :mod:`psdr_cli.mitsuba_scene`; split OBJ objects are expanded into their parts.
    """
    exp = mitsuba_scene.resolve(exp)
    if exp.scene.mitsuba is not None:
        return build_xml_scene(exp, objects or {}, cameras)
    cfg = exp.scene
    built = build_objects(exp)
    for name, (V, F) in (objects or {}).items():
        built[name] = ObjectMesh(name, np.asarray(V, float), np.asarray(F, np.int64), built[name].edges,
                                 built[name].config)
    d = {"type": "scene", "integrator": {"type": "path", "max_depth": cfg.max_depth}}
    for i, cam in enumerate(cameras or cfg.cameras):
        d[f"sensor_{i:03d}"] = sensor_dict(cam, cfg.width, cfg.height)
    for i, em in enumerate(cfg.emitters):
        d[f"emitter_{i:02d}"] = emitter_dict(em, str(exp.file))
    for name, om in built.items():
        try:
            d[name] = mitsuba_mesh(name, om.vertices, om.faces, bsdf_dict(om.config), om.config.smooth)
        except Exception as exc:  # noqa: BLE001 - Mitsuba rejects a BSDF parameter value
            raise ConfigError(exp.file, om.config.key + ".bsdf",
                              f"Mitsuba rejected the BSDF: {str(exc).splitlines()[0]}") from None
    try:
        mi_scene = mi.load_dict(d)
    except Exception as exc:  # noqa: BLE001 - Mitsuba rejects a parameter value
        raise ConfigError(exp.file, "scene", f"Mitsuba could not build the scene: {str(exc).splitlines()[0]}") from None
    return Scene(mi_scene, cfg, built)


def build_xml_scene(exp: Experiment, objects: dict, cameras: list | None) -> Scene:
    """The Mitsuba scene of a resolved XML experiment (see :mod:`psdr_cli.mitsuba_scene`)."""
    cfg = exp.scene
    unknown = [name for name in objects if name not in {o.name for o in cfg.objects}]
    if unknown:
        raise ConfigError(exp.file, "scene", f"no object '{unknown[0]}' in {cfg.mitsuba.file.name}")
    sensors = None
    if cameras or cfg.mitsuba.cameras_given:
        sensors = [sensor_dict(cam, cfg.width, cfg.height) for cam in (cameras or cfg.cameras)]
    entries, geometry = mitsuba_scene.scene_entries(exp, objects, sensors)
    d = {"type": "scene", "integrator": {"type": "path", "max_depth": cfg.max_depth}, **entries}
    try:
        mi_scene = mi.load_dict(d)
    except Exception as exc:  # noqa: BLE001
        raise ConfigError(cfg.mitsuba.file, "", f"Mitsuba could not rebuild the scene: {str(exc).splitlines()[0]}") from None
    built = {o.name: ObjectMesh(o.name, *geometry[o.name], o.edges, o) for o in cfg.objects}
    return Scene(mi_scene, cfg, built)
