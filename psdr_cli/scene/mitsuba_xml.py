"""Mitsuba 3 XML scenes as psdr scenes (``scene: {mitsuba: scene.xml}``).

The XML is read with ``mi.load_file(file, optimize=False, **params)`` (without Mitsuba's merging
of shapes that share a BSDF, so every shape keeps its id); what psdr can differentiate is taken
from it and the scene is rebuilt with ``mi.load_dict`` under psdr's naming:

- **triangle meshes** (``obj``, ``ply``, ``serialized``, ``rectangle``, ``cube``, ...: every shape
  with ``is_mesh()`` that does not emit) become scene objects named by their XML ``id`` (shapes
  without one: ``<plugin>_<k>``, numbered past any id the XML gives). An id must be usable as a
  psdr object name (:func:`psdr_cli.config.name_problem`: not starting with ``@``, psdr's own
  ids for cameras, emitters and the integrator; not ``type``; no ``.``). Each is rebuilt as an
  ``mi.Mesh`` from its world-space vertex positions, faces, and (when present) vertex normals
  and texture coordinates, with its own BSDF instance, so ``<id>.vertex_positions`` is a
  differentiable parameter. Smooth shading = the shape has vertex normals that are not just its
  face normals; ``edges`` = true unless ``scene.objects: {id: {edges: false}}``. Vertices must
  be finite and within ±MAX_COORD; degenerate triangles are dropped (a warning), all of them is
  an error.
- **emitting shapes** (area lights on any shape) stay as they are: static light geometry, like
  the YAML ``area`` emitter (cameras see them, they cast shadows, their edges are not sampled).
- **environment emitters** ``envmap``, ``constant`` and ``sunsky`` keep their XML ``to_world``
  (the scene keeps its own frame) and are named ``@emitter_00`` (``envmap_rotate`` finds them).
- **analytic shapes** (``sphere``, ``disk``, ``cylinder``, instances of a ``shapegroup``, ...)
  are rendered, with one warning each: psdr cannot sample their edges, so silhouettes and
  shadows of them carry no derivative.
- **refused** with one error line: non-``perspective`` sensors, delta emitters (``point``, ``spot``, ``directional``, ``projector``), ``mask`` and
  ``null`` BSDFs (surfaces rays pass through), participating media (on a shape or a sensor),
  more than one environment, NaN or infinite values in a BSDF or emitter (its textures included).
- **replaced**: the XML integrator (psdr's estimators render; its ``max_depth`` is the default of
  ``scene.max_depth``), the sampler (``estimator.spp``) and the film's reconstruction filter
  (psdr integrates box pixels). Sensors keep their ``to_world``, horizontal field of view, clip
  planes and principal point offset; ``scene.film`` may replace the film size, ``scene.cameras`` the sensors.

Parse errors become one line ``scene.xml: line N, column M: message``.
"""
from __future__ import annotations

import hashlib
import re
import sys
from dataclasses import dataclass, field, replace
from pathlib import Path
from xml.etree import ElementTree

import mitsuba as mi
import numpy as np

from . import meshes
from ..config.cameras_section import CameraConfig
from ..config.emitters import EmitterConfig
from ..config.experiment_file import Experiment
from ..config.limits import MAX_COORD, MAX_FILM, MAX_PRINCIPAL_OFFSET, MAX_TEXELS
from ..config.objects import BsdfConfig, MeshSpec, ObjectConfig
from ..config.scene_section import SceneConfig
from ..config.scene_ids import emitter_id, name_problem, sensor_id
from ..errors import ConfigError
from ..support import backend, fileio
from ..support.jitarray import jit_array

#: Emitter classes psdr handles → the YAML emitter type they correspond to.
EMITTERS = {"AreaLight": "area", "EnvironmentMapEmitter": "envmap", "ConstantBackgroundEmitter": "constant",
            "SunskyEmitter": "sky"}
#: Delta emitters: refused (their hard shadows have no boundary samples in psdr).
DELTA_EMITTERS = {"PointLight": "point", "SpotLight": "spot", "DirectionalEmitter": "directional",
                  "Projector": "projector"}
#: BSDFs that let rays pass through a surface: refused (the boundary terms assume opaque or
#: refracting surfaces).
PASS_THROUGH_BSDFS = {"MaskBSDF": "mask", "Null": "null"}
#: BSDF classes → plugin names (the boundary code tells transmissive BSDFs by these names).
BSDF_NAMES = {"SmoothDiffuse": "diffuse", "RoughConductor": "roughconductor", "SmoothConductor": "conductor",
              "SmoothDielectric": "dielectric", "RoughDielectric": "roughdielectric",
              "ThinDielectric": "thindielectric", "Principled": "principled", "PrincipledThin": "principledthin",
              "SmoothPlastic": "plastic", "RoughPlastic": "roughplastic", "TwoSidedBRDF": "twosided"}
ANALYTIC = {"Sphere": "sphere", "Disk": "disk", "Cylinder": "cylinder", "Instance": "instance",
            "BSplineCurve": "bsplinecurve", "LinearCurve": "linearcurve", "SDFGrid": "sdfgrid",
            "ShapeGroup": "shapegroup", "Ellipsoids": "ellipsoids", "EllipsoidsMesh": "ellipsoidsmesh"}


#: Files of an XML scene whose size is checked before Mitsuba decodes them.
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".exr", ".hdr", ".rgbe", ".pfm", ".ppm", ".pgm", ".tga", ".bmp")


def warn_stderr(message: str):
    print(f"warning: {message}", file=sys.stderr)


# --------------------------------------------------------------------------------------------
# Reading the XML
# --------------------------------------------------------------------------------------------
_POSITION = re.compile(r"\(line (\d+), col(?:umn)? (\d+)\)")


def xml_error(exc: Exception, file: Path) -> ConfigError:
    """Mitsuba's parse or plugin error as one line ``file: line N, column M: message``."""
    text = " ".join(str(exc).split()) or type(exc).__name__
    text = re.sub(r"^\[[^\]]*\]\s*", "", text)  # "[parser.cpp:1087] "
    named = re.search(r'(?:At|loading|XML file)\s+"?([^"]+?)"?\s*(?:\(line|failed|:)', text)
    where_file = Path(named.group(1)) if named else file
    if not where_file.is_absolute():
        where_file = file.parent / where_file if not where_file.exists() else where_file.resolve()
    pos = _POSITION.search(text)
    message = text
    if pos:
        message = text[pos.end():].lstrip(": ").strip() or text[:pos.start()]
        # "Parsing of XML file "x" failed: Error parsing end element tag (line 5, col 1)"
        message = re.sub(r'^Parsing of XML file "[^"]*" failed:\s*', "", message)
        if not message:
            message = re.sub(r'^Parsing of XML file "[^"]*" failed:\s*', "", text[:pos.start()]).strip()
        return ConfigError(where_file, f"line {pos.group(1)}, column {pos.group(2)}", message.strip())
    return ConfigError(where_file, "", re.sub(r'^"[^"]*":\s*', "", message))


def named_files(src) -> list:
    """[(file, the XML file naming it)] for every file the XML scene ``src`` reads, as its text
    names them: the XML itself, the files it ``<include>``s (recursively) and every file a plugin
    is given (a ``filename`` attribute or ``<string name="filename">``: meshes, textures,
    environment maps, spectra), ``$name`` replaced by ``src.params`` or the XML's ``<default>``s,
    relative to the main XML's folder (where Mitsuba resolves them) or the naming file's. Files
    that do not exist are left out (Mitsuba reports them)."""
    main = Path(src.file).resolve()
    found, todo, params = {main: main}, [main], {}
    while todo:
        xml = todo.pop(0)
        try:
            elements = list(ElementTree.parse(xml).getroot().iter())
        except (ElementTree.ParseError, OSError):
            continue  # Mitsuba says what is wrong with it
        params.update({e.get("name"): e.get("value") for e in elements if e.tag == "default"})
        params.update(src.params)
        for e in elements:
            name = e.get("filename")
            if e.tag == "string" and e.get("name") == "filename":
                name = e.get("value")
            if not name:
                continue
            name = re.sub(r"\$(\w+)", lambda m: str(params.get(m.group(1), m.group(0))), name)
            file = next((p.resolve() for p in (main.parent / name, xml.parent / name) if p.is_file()), None)
            if file is not None and file not in found:
                found[file] = xml
                if e.tag == "include":
                    todo.append(file)
    return list(found.items())


def scene_files(src) -> list:
    """Every file the XML scene ``src`` reads (:func:`named_files`), sorted."""
    return sorted(file for file, _ in named_files(src))


#: Byte-order marks of the UTF-16 and UTF-32 files Mitsuba's XML parser (pugixml) converts itself.
_OTHER_BOMS = (b"\x00\x00\xfe\xff", b"\xff\xfe\x00\x00", b"\xfe\xff", b"\xff\xfe")


def check_utf8(file: Path):
    """Refuse an XML file that is not valid UTF-8, with the line and column of its first bad byte
    (Mitsuba loads it, but its ids and names cannot be read back as text). Files with a UTF-16/32
    byte-order mark or another declared ``encoding`` are left to Mitsuba's parser."""
    try:
        data = file.read_bytes()
    except OSError:
        return  # Mitsuba reports it
    head = re.match(rb"\s*<\?xml[^>]*?encoding\s*=\s*[\"']([^\"']+)", data[:200])
    if data.startswith(_OTHER_BOMS) or (head and head.group(1).lower().replace(b"_", b"-") not in (b"utf-8", b"utf8")):
        return
    try:
        data.decode("utf-8")
    except UnicodeDecodeError as exc:
        line, line_start = data.count(b"\n", 0, exc.start) + 1, data.rfind(b"\n", 0, exc.start) + 1
        column = len(data[line_start:exc.start].decode("utf-8", "replace")) + 1
        raise ConfigError(file, f"line {line}, column {column}",
                          f"not valid UTF-8 (byte 0x{data[exc.start]:02x}); save the file as UTF-8") from None


def load_xml(src, yaml_file: str | None = None) -> mi.Scene:
    """``mi.load_file(src.file, **src.params)``; any failure is one :class:`ConfigError` line (a
    ``params`` entry the XML does not use names the experiment file's key). The XML files
    (``src.file`` and its ``<include>``s) must be UTF-8 (:func:`check_utf8`); the images the XML
    names are refused first when they are too large to decode (:data:`MAX_TEXELS`)."""
    for file, xml in named_files(src):
        if file == Path(src.file).resolve() or file.suffix.lower() == ".xml":
            check_utf8(file)
        problem = fileio.image_too_large(file, MAX_TEXELS) if file.suffix.lower() in IMAGE_SUFFIXES else None
        if problem:
            raise ConfigError(xml, "", f"image {problem}")
    try:
        with backend.decoding_threads():  # the XML may name EXR files
            return mi.load_file(str(src.file), optimize=False, **src.params)
    except Exception as exc:  # noqa: BLE001 - Mitsuba reports XML and plugin errors as RuntimeError
        unused = re.findall(r"\$(\S+?)=", str(exc)) if "unused parameters" in str(exc) else []
        if unused and yaml_file:
            raise ConfigError(yaml_file, f"scene.params.{unused[0]}",
                              f"{src.file.name} does not use ${unused[0]}") from None
        raise xml_error(exc, src.file) from None


@dataclass
class XmlObject:
    """A triangle mesh of the XML: world-space arrays as Mitsuba loaded them and its BSDF."""
    name: str
    V: np.ndarray
    F: np.ndarray
    normals: np.ndarray | None
    texcoords: np.ndarray | None
    bsdf: object


@dataclass
class XmlScene:
    """What psdr takes from an XML scene (see the module docstring)."""
    sensors: list                     # (to_world 4×4, x_fov, near, far, principal point offset) per XML sensor
    cameras: list                     # CameraConfig per XML sensor (origin, target, up, fov, principal_point)
    size: tuple | None                # film (width, height) of the XML sensors
    emitters: list                    # EmitterConfig per emitter (area lights included)
    environment: dict = field(default_factory=dict)   # @emitter_NN -> environment emitter instance
    shapes: dict = field(default_factory=dict)        # id -> light, analytic shape or shapegroup (kept)
    objects: dict = field(default_factory=dict)       # id -> XmlObject
    max_depth: int | None = None
    warnings: list = field(default_factory=list)
    digest: str = ""


def _matrix(transform) -> np.ndarray:
    return np.array(transform.matrix, dtype=np.float64).reshape(4, 4)


def _unit(v):
    v = np.asarray(v, float)
    return v / np.linalg.norm(v)


def _shape_names(mi_scene, taken=()) -> list:
    """XML id of every shape (shapes without one: ``<plugin>_<k>``, numbered per plugin, skipping
    the ids the XML gives and the names in ``taken``)."""
    used = set(taken) | {shape.id() for shape in mi_scene.shapes() if shape.id()}
    counts, names = {}, []
    for shape in mi_scene.shapes():
        if shape.id():
            names.append(shape.id())
            continue
        kind = shape.class_name().lower()
        while f"{kind}_{counts.get(kind, 0)}" in used:
            counts[kind] = counts.get(kind, 0) + 1
        names.append(f"{kind}_{counts.get(kind, 0)}")
        counts[kind] = counts.get(kind, 0) + 1
    return names


def shape_groups(mi_scene) -> dict:
    """{id: shapegroup} of the scene (instances refer to them; ``mi_scene.shapes()`` lists only
    the instances)."""
    found = {}

    class Collect(mi.TraversalCallback):
        def put(self, name, obj, *args):
            if isinstance(obj, mi.Object) and obj.class_name().startswith("ShapeGroup"):
                found[name] = obj

    mi_scene.traverse(Collect())
    return found


def nonfinite_parameter(obj, checked: set) -> str | None:
    """Name of the first parameter of a Mitsuba object (a BSDF or an emitter: its values and
    textures) holding NaN or infinite values, or None; objects in ``checked`` (by pointer) are
    skipped and each object checked is added to it."""
    if obj is None or obj.ptr in checked:
        return None
    checked.add(obj.ptr)
    params = mi.traverse(obj)
    for key in params.keys():
        try:
            values = np.asarray(params[key])
        except Exception:  # noqa: BLE001 - transforms and other non-array parameters
            continue
        if values.dtype.kind == "f" and not np.isfinite(values).all():
            return key
    return None


def flat_normals(V, F, normals, cos_tol: float = 1 - 1e-5) -> bool:
    """Whether every vertex normal equals the normal of each face using the vertex (a flat-shaded
    mesh stored with split vertices). Such meshes are flat for psdr (``smooth: false``): its
    smooth-shading boundary handling assumes normals interpolated across edges."""
    n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)
    N = normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-30)
    return bool(all((np.einsum("ij,ij->i", N[F[:, k]], n) > cos_tol).all() for k in range(3)))


def bsdf_name(bsdf) -> str:
    """Plugin name of a BSDF instance; transmissive BSDFs psdr does not list are reported as
    ``dielectric`` so that their concave edges stay in the boundary terms."""
    name = BSDF_NAMES.get(bsdf.class_name(), bsdf.class_name().lower())
    if mi.has_flag(bsdf.flags(), mi.BSDFFlags.Transmission) and name not in (
            "dielectric", "roughdielectric", "thindielectric"):
        return "dielectric"
    return name


def read_scene(src, yaml_file: str, rotates: bool = False) -> XmlScene:
    """Read and check the XML scene ``src`` (``scene.mitsuba`` of the experiment file
    ``yaml_file``; a variant must be active). ``rotates``: the experiment's parameter turns
    something about the up axis (a warning when the XML's frame is not z-up)."""
    mi_scene = load_xml(src, yaml_file)
    warnings = []
    sensors, cameras, sizes = read_sensors(mi_scene, src, warnings, rotates)
    emitters, environment = read_emitters(mi_scene, src.file)
    shapes, objects = read_shapes(mi_scene, src.file, emitters, warnings)
    unknown = [n for n in src.edges if n not in objects]
    if unknown:
        raise ConfigError(yaml_file, f"scene.objects.{unknown[0]}",
                          f"no mesh shape '{unknown[0]}' in {src.file.name} (meshes: {', '.join(objects) or 'none'})")
    max_depth = read_max_depth(mi_scene, src, warnings)
    return XmlScene(sensors, cameras, sizes.pop() if len(sizes) == 1 else None, emitters, environment, shapes,
                    objects, max_depth, warnings, scene_digest(src, objects))


def read_sensors(mi_scene, src, warnings: list, rotates: bool) -> tuple:
    """(sensors, cameras, film sizes) of the XML: each perspective sensor's (to_world, x_fov,
    near, far, principal point offset) and its :class:`CameraConfig`, none when ``scene.cameras``
    replace them (the film size is then the first sensor's); warnings appended to ``warnings``
    (``rotates``: see :func:`read_scene`)."""
    xml = src.file
    films = [tuple(int(s) for s in sensor.film().size()) for sensor in mi_scene.sensors() if sensor.film()]
    for i, (w, h) in enumerate(films[:1] if src.cameras_given else films):
        if src.film is None and not (1 <= w <= MAX_FILM and 1 <= h <= MAX_FILM):  # as scene.film's limits
            raise ConfigError(xml, f"sensor {i}", f"film {w}×{h}: expected a width and height in [1, {MAX_FILM}] "
                                                  f"(a resource limit; or give scene.film)")
    if src.cameras_given:   # scene.cameras replace the XML's sensors; the film size is the first one's
        return [], [], {films[0] if films else (128, 128)}
    sensors, cameras, sizes = [], [], set(films)
    for i, sensor in enumerate(mi_scene.sensors()):
        sensors.append(read_sensor(sensor, i, src, warnings))
        M, fov, _, _, offset = sensors[-1]
        origin = M[:3, 3]
        cameras.append(CameraConfig(origin=tuple(float(c) for c in origin),
                                    target=tuple(float(c) for c in origin + _unit(M[:3, 2])),
                                    up=tuple(float(c) for c in _unit(M[:3, 1])), fov=fov,
                                    principal_point=offset))
    if not sensors:
        raise ConfigError(xml, "", "has no sensor (add a perspective <sensor>, or give scene.cameras)")
    if len(sizes) > 1 and src.film is None:
        raise ConfigError(xml, "", f"its sensors have different film sizes {sorted(sizes)}; give scene.film")
    if not src.up_given:
        axis = int(np.argmax(np.abs(cameras[0].up)))
        uses_up = src.cameras_given or rotates
        if axis != 2 and uses_up:
            name = "xyz"[axis]
            warnings.append(f"{xml.name}: its first camera is {name}-up but scene.up is [0, 0, 1] (the default "
                            f"of rotation axes and camera up); set scene.up for this scene's frame")
    return sensors, cameras, sizes


def read_sensor(sensor, i: int, src, warnings: list) -> tuple:
    """(to_world 4×4, x_fov, near, far, principal point offset) of XML sensor ``i``, checked: a
    perspective camera without a medium, its offset within the limits."""
    xml = src.file
    kind = sensor.class_name()
    what = f"sensor {i}" + (f" '{sensor.id()}'" if sensor.id() else "")
    if sensor.get_medium() is not None:
        raise ConfigError(xml, what, "participating media are not supported (remove the sensor's <medium> or <ref>)")
    if kind != "PerspectiveCamera":
        raise ConfigError(xml, what, f"'{kind}' is not supported (psdr needs perspective sensors: its film "
                                     f"projection and camera connections assume a pinhole)")
    p = mi.traverse(sensor)
    offset = tuple(float(p[f"principal_point_offset_{a}"][0]) for a in "xy")
    if not all(abs(o) <= MAX_PRINCIPAL_OFFSET for o in offset):
        raise ConfigError(xml, what, f"principal point offset {list(offset)}: expected offsets within "
                                     f"±{MAX_PRINCIPAL_OFFSET:g} (fractions of the film width and height)")
    film = sensor.film()
    if tuple(film.crop_size()) != tuple(film.size()) and src.film is None:
        warnings.append(f"{xml.name}: {what}: the film's crop window is ignored (psdr renders the whole film)")
    return _matrix(p["to_world"]), float(p["x_fov"][0]), float(sensor.near_clip()), float(sensor.far_clip()), offset


def read_emitters(mi_scene, xml: Path) -> tuple:
    """(emitters, {@emitter_NN: environment emitter}) of the XML: delta and unknown emitters
    refused, at most one environment, its values finite (area lights are counted with their
    shapes)."""
    emitters, environment = [], {}
    for em in mi_scene.emitters():
        kind = em.class_name()
        what = f"emitter '{em.id()}'" if em.id() else f"emitter {kind}"
        if kind in DELTA_EMITTERS:
            raise ConfigError(xml, what, f"'{DELTA_EMITTERS[kind]}' lights are not supported (delta lights: psdr's "
                                         f"boundary terms need area or environment emitters; its hard shadows would "
                                         f"have no derivative)")
        if kind not in EMITTERS:
            raise ConfigError(xml, what, f"'{kind}' is not supported (psdr handles area, envmap, constant and sunsky "
                                         f"emitters)")
        if kind == "AreaLight":
            continue
        bad = nonfinite_parameter(em, set())
        if bad:
            raise ConfigError(xml, what, f"'{bad}' has NaN or infinite values (the environment map or a value of "
                                         f"the XML)")
        environment[emitter_id(len(environment))] = em
        emitters.append(EmitterConfig(type=EMITTERS[kind], key=what))
    if len(environment) > 1:
        raise ConfigError(xml, "", "has more than one environment emitter (psdr allows one envmap, constant or sunsky)")
    return emitters, environment


def read_shapes(mi_scene, xml: Path, emitters: list, warnings: list) -> tuple:
    """({id: kept shape}, {id: :class:`XmlObject`}) of the XML: emitting shapes (their area lights
    appended to ``emitters``), analytic shapes (a warning each) and shapegroups are kept as they
    are; triangle meshes become the objects psdr differentiates."""
    shapes, objects, checked = shape_groups(mi_scene), {}, set()
    for name in shapes:
        if name_problem(name):
            raise ConfigError(xml, f"shapegroup '{name}'", f"id {name_problem(name)}")
        refuse_instances_on_cuda(name, mi.variant(), xml)
    for name, shape in zip(_shape_names(mi_scene, shapes), mi_scene.shapes()):
        what = f"shape '{name}'"
        check_shape(shape, name, xml, checked, duplicate=name in objects or name in shapes)
        if shape.emitter() is not None:
            shapes[name] = shape
            emitters.append(EmitterConfig(type="area", key=what))
            continue
        if not shape.is_mesh():
            kind = ANALYTIC.get(shape.class_name(), shape.class_name().lower())
            warnings.append(f"{xml.name}: {what} is an analytic '{kind}': it is rendered, but psdr cannot sample "
                            f"its edges, so its silhouette and shadows have no derivative (use a mesh)")
            shapes[name] = shape
            continue
        objects[name] = xml_object(shape, name, xml, warnings)
    return shapes, objects


def refuse_instances_on_cuda(group: str, variant: str, xml: Path):
    """Shapegroups (and so their instances) are refused on CUDA variants: psdr rebuilds a scene
    from the loaded XML's objects, and ``mi.load_dict`` of a rebuilt scene holding a shapegroup
    instance crashes Mitsuba's CUDA variant (docs/benchmarks/gpu_first_run.md); the LLVM variants
    render it."""
    if variant.startswith("cuda"):
        raise ConfigError(xml, f"shapegroup '{group}'", f"instances of a shapegroup crash Mitsuba's {variant} "
                          "when psdr rebuilds the scene; use variant llvm_ad_rgb or replace the instances by meshes")


def check_shape(shape, name: str, xml: Path, checked: set, duplicate: bool):
    """A shape psdr can render: its id valid, no medium, no pass-through BSDF, its id not taken
    (``duplicate``), finite BSDF and emitter values (``checked``: the BSDFs and emitters already
    checked)."""
    what = f"shape '{name}'"
    if name_problem(name):
        raise ConfigError(xml, what, f"id {name_problem(name)}")
    if shape.interior_medium() is not None or shape.exterior_medium() is not None:
        raise ConfigError(xml, what, "participating media are not supported")
    bsdf = shape.bsdf()
    if bsdf is not None and bsdf.class_name() in PASS_THROUGH_BSDFS:
        raise ConfigError(xml, what, f"'{PASS_THROUGH_BSDFS[bsdf.class_name()]}' BSDFs are not supported (rays pass "
                                     f"through the surface; psdr's boundary terms assume opaque or refracting surfaces)")
    if duplicate:
        raise ConfigError(xml, what, "duplicate shape id")
    for part, obj in (("BSDF", bsdf), ("emitter", shape.emitter())):
        bad = nonfinite_parameter(obj, checked)
        if bad:
            raise ConfigError(xml, what, f"{part} parameter '{bad}' has NaN or infinite values (a texture or a value "
                                         f"of the XML)")


def xml_object(shape, name: str, xml: Path, warnings: list) -> XmlObject:
    """The world-space arrays of a triangle mesh of the XML, checked: not empty, finite and within
    float32's useful range; degenerate triangles dropped (with a warning); per-face normals on
    split vertices read as flat shading."""
    what = f"shape '{name}'"
    V = np.array(shape.vertex_positions_buffer(), np.float64).reshape(-1, 3)
    F = np.array(shape.faces_buffer(), np.int64).reshape(-1, 3)
    if len(F) == 0:
        raise ConfigError(xml, what, "mesh is empty")
    if not np.isfinite(V).all():
        raise ConfigError(xml, what, f"mesh has {int((~np.isfinite(V).all(axis=1)).sum())} vertices with NaN or "
                                     f"infinite coordinates")
    far = (np.abs(V) > MAX_COORD).any(axis=1)
    if far.any():
        raise ConfigError(xml, what, f"mesh has {int(far.sum())} vertices with world coordinates beyond "
                                     f"±{MAX_COORD:g} (e.g. {V[far][0].tolist()}; float32 rendering needs smaller "
                                     f"values)")
    bad = meshes.degenerate_faces(V, F)
    if bad.all():
        raise ConfigError(xml, what, f"mesh has only degenerate (zero-area) triangles ({len(F)})")
    if bad.any():
        warnings.append(f"{xml.name}: {what}: {int(bad.sum())} degenerate (zero-area) triangles of {len(F)} dropped")
        F = F[~bad]
    normals = np.array(shape.vertex_normals_buffer(), np.float64).reshape(-1, 3) if shape.has_vertex_normals() else None
    if normals is not None and flat_normals(V, F, normals):
        normals = None  # per-face normals on split vertices (a cube, a rectangle): flat shading
    uv = np.array(shape.vertex_texcoords_buffer(), np.float64).reshape(-1, 2) if shape.has_vertex_texcoords() else None
    return XmlObject(name, V, F, normals, uv, shape.bsdf())


def read_max_depth(mi_scene, src, warnings: list) -> int | None:
    """The XML integrator's ``max_depth`` (psdr renders with its own estimators; this is the
    default of ``scene.max_depth``), or None (with a warning unless the experiment sets it)."""
    m = re.search(r"max_depth\s*=\s*(-?\d+)", str(mi_scene.integrator()))
    if m and int(m.group(1)) >= 1:
        return int(m.group(1))
    if not src.max_depth_given:
        warnings.append(f"{src.file.name}: the integrator's max_depth is {m.group(1) if m else 'not given'}; psdr "
                        f"uses scene.max_depth = 2 (set it in the experiment)")
    return None


def scene_digest(src, objects: dict) -> str:
    """16 hex digits of the XML's bytes, its ``$name`` substitutions and its meshes' arrays."""
    h = hashlib.sha256(src.file.read_bytes())
    h.update(repr(sorted(src.params.items())).encode())
    for name, o in objects.items():
        h.update(name.encode())
        h.update(np.ascontiguousarray(o.V).tobytes())
        h.update(np.ascontiguousarray(o.F).tobytes())
    return h.hexdigest()[:16]


# --------------------------------------------------------------------------------------------
# Resolving an experiment: the scene section filled in from the XML (and split OBJ objects)
# --------------------------------------------------------------------------------------------
def object_config(name: str, o: XmlObject, src) -> ObjectConfig:
    return ObjectConfig(name=name, mesh=MeshSpec(key=f"scene.mitsuba#{name}", shape="mitsuba",
                                                 params={"id": name, "digest": ""}),
                        key=f"scene.objects.{name}", bsdf=BsdfConfig(bsdf_name(o.bsdf), {}),
                        edges=src.edges.get(name, True), smooth=o.normals is not None)


def scene_config(exp: Experiment, warn=warn_stderr) -> SceneConfig:
    """The experiment's scene with its XML read: cameras (unless ``scene.cameras`` is given), film
    size, emitters and objects filled in (called once, when the experiment is loaded:
    :mod:`psdr_cli.experiment.load`). ``warn`` receives one line per item psdr renders but cannot
    differentiate."""
    scene, src = exp.scene, exp.scene.mitsuba
    rotates = exp.parameter is not None and exp.parameter.kind in ("rotate", "envmap_rotate")
    try:
        xs = read_scene(src, str(exp.file), rotates)
    except UnicodeDecodeError:  # an encoding check_utf8 leaves to Mitsuba, which passed the bytes through
        raise ConfigError(src.file, "", "an id or name in it is not valid UTF-8 once read by Mitsuba "
                                        "(save the file as UTF-8)") from None
    for message in xs.warnings:
        warn(message)
    width, height = src.film or xs.size
    objects = []
    for name, o in xs.objects.items():
        cfg = object_config(name, o, src)
        cfg.mesh.params["digest"] = xs.digest
        objects.append(cfg)
    max_depth = scene.max_depth if src.max_depth_given or xs.max_depth is None else xs.max_depth
    geometry = {name: (o.V, o.F) for name, o in xs.objects.items()}
    return replace(scene, width=width, height=height, max_depth=max_depth,
                   cameras=scene.cameras if src.cameras_given else xs.cameras, emitters=xs.emitters,
                   objects=objects, mitsuba=replace(src, digest=xs.digest, geometry=geometry))


# --------------------------------------------------------------------------------------------
# Building the Mitsuba scene
# --------------------------------------------------------------------------------------------
def mesh(name: str, V, F, bsdf, *, normals=None, texcoords=None, smooth: bool = False, emitter=None):
    """``mi.Mesh`` from arrays with a BSDF instance (and optionally an area ``emitter`` instance);
    ``normals`` (or ``smooth``: normals computed by Mitsuba) and ``texcoords`` as given."""
    props = mi.Properties()
    if bsdf is not None:
        props["bsdf"] = bsdf
    if emitter is not None:
        props["emitter"] = emitter
    m = mi.Mesh(name, len(V), len(F), props, normals is not None or smooth, texcoords is not None)
    params = mi.traverse(m)
    params["vertex_positions"] = jit_array(mi.Float, np.ravel(V))
    params["faces"] = jit_array(mi.UInt32, np.ravel(F))
    if texcoords is not None:
        params["vertex_texcoords"] = jit_array(mi.Float, np.ravel(texcoords))
    params.update()
    if normals is not None:  # after the update, which recomputes normals from the positions
        params["vertex_normals"] = jit_array(mi.Float, np.ravel(normals))
        params.update()
    return m


def sensor_dicts(xs: XmlScene, width: int, height: int) -> list:
    """Perspective sensors of the XML (to_world, horizontal fov, clip planes, principal point
    offset when not centred) with a box-filtered film of the given size (the whole film: an
    offset is a fraction of it, as Mitsuba's without a crop window)."""
    out = []
    for M, fov, near, far, (ox, oy) in xs.sensors:
        d = {"type": "perspective", "fov": fov, "fov_axis": "x", "to_world": mi.ScalarTransform4f(M),
             "near_clip": near, "far_clip": far,
             "film": {"type": "hdrfilm", "width": width, "height": height, "pixel_format": "rgb",
                      "rfilter": {"type": "box"}},
             "sampler": {"type": "independent"}}
        if ox or oy:
            d["principal_point_offset_x"], d["principal_point_offset_y"] = ox, oy
        out.append(d)
    return out


def scene_entries(exp, overrides: dict, sensors: list | None):
    """(``mi.load_dict`` entries without the integrator, {id: (V, F)} of the objects) of a
    loaded XML experiment (its ``scene`` and ``file``: :func:`psdr_cli.scene.build.build_scene`).
    ``overrides``: {id: (V, F)} replacing meshes (flat or, for shapes with normals, smooth
    shading computed by Mitsuba); ``sensors``: sensor dicts replacing the XML's. The XML is read
    again (:func:`read_scene`, its warnings given at load): each scene gets its own BSDF and
    emitter instances, which an optimisation changes."""
    xs = read_scene(exp.scene.mitsuba, str(exp.file))
    cfg = exp.scene
    d = {}
    for i, s in enumerate(sensors if sensors is not None else sensor_dicts(xs, cfg.width, cfg.height)):
        d[sensor_id(i)] = s
    d.update(xs.environment)
    d.update(xs.shapes)
    geometry = {}
    for name, o in xs.objects.items():
        if name in overrides:
            V, F = (np.asarray(a) for a in overrides[name])
            d[name] = mesh(name, V, F, o.bsdf, smooth=o.normals is not None)
        else:
            V, F = o.V, o.F
            d[name] = mesh(name, V, F, o.bsdf, normals=o.normals, texcoords=o.texcoords)
        geometry[name] = (np.asarray(V, float), np.asarray(F, np.int64))
    return d, geometry
