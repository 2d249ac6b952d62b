"""``scene``: the film, path depth, cameras, emitters and objects, or a Mitsuba 3 XML scene."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from .cameras_section import parse_cameras
from .emitters import parse_emitter
from .limits import MAX_DEPTH, MAX_FILM
from .objects import parse_object
from .values import Parser, Section, Where, boolean, describe, integer, list_of, path_relative_to, unit, vector


@dataclass
class MitsubaSource:
    """``scene: {mitsuba: scene.xml}``: a Mitsuba 3 XML scene (read by :mod:`psdr_cli.scene.mitsuba_xml`).

    ``params``: ``$name`` substitutions; ``film``: (width, height) replacing the XML film's size;
    ``edges``: {shape id: bool} overrides; ``up``: the scene's up axis (default of camera ``up``
    and of rotation axes); ``up_given``: whether the file set it. ``digest`` and ``geometry``
    are filled when the experiment is loaded (:mod:`psdr_cli.experiment.load`), once the XML has been
    read: ``geometry`` holds the world-space (V, F) of each XML mesh by id, as read then (what was
    loaded, not what the file says: no part of a run's fingerprint or a target's key,
    :func:`psdr_cli.run_folder.fingerprint.scene_identity`)."""
    file: Path
    params: dict = field(default_factory=dict)
    film: tuple | None = None
    edges: dict = field(default_factory=dict)
    up: tuple = (0.0, 0.0, 1.0)
    up_given: bool = False
    cameras_given: bool = False
    max_depth_given: bool = False
    digest: str = ""
    geometry: dict = field(default_factory=dict, compare=False, repr=False)


@dataclass
class SceneConfig:
    width: int
    height: int
    max_depth: int
    cameras: list
    emitters: list
    objects: list
    mitsuba: MitsubaSource | None = None   # an XML scene: cameras, emitters, objects come from it
    hide_background: bool = False          # camera rays that leave the scene see black (a dataset's masked views)


def _xml_param(value, where):
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float, str)):
        return str(value)
    raise where.fail(f"expected a number, a string or true/false, got {describe(value)}")


def parse_mitsuba_scene(sec: Section, where: Where, base: Path) -> SceneConfig:
    """``scene: {mitsuba: file.xml, params, film, max_depth, cameras, up, objects}``. The XML
    itself is read later (it needs Mitsuba): its sensors, emitters and shapes fill the scene."""
    file = sec.get("mitsuba", path_relative_to(base))
    if file.suffix.lower() != ".xml":
        raise where.child("mitsuba").fail(f"expected a Mitsuba 3 scene file (.xml), got '{file.name}'")
    if not file.is_file():
        raise where.child("mitsuba").fail(f"file not found: {file}")
    src = MitsubaSource(file=file)
    params = sec.get("params", lambda v, w: v, {})
    if not isinstance(params, dict):
        raise where.child("params").fail(f"expected a mapping of $name: value, got {describe(params)}")
    src.params = {str(k): _xml_param(v, where.child("params").child(str(k))) for k, v in params.items()}
    if sec.has("film"):
        film = Section(sec.get("film", lambda v, _: v), where.child("film"))
        src.film = (film.get("width", integer(1, MAX_FILM)), film.get("height", integer(1, MAX_FILM)))
        film.done()
    src.up_given = sec.has("up")
    src.up = unit(sec.get("up", vector(3, nonzero=True), src.up))
    src.cameras_given = sec.has("cameras")
    src.max_depth_given = sec.has("max_depth")
    objects = sec.get("objects", lambda v, w: v, {})
    if not isinstance(objects, dict):
        raise where.child("objects").fail(f"expected a mapping of XML shape ids to {{edges: ...}}, got "
                                          f"{describe(objects)}")
    for name, entry in objects.items():
        o = Section(entry, where.child("objects").child(str(name)))
        src.edges[str(name)] = o.get("edges", boolean, True)
        o.done()
    scene = SceneConfig(
        width=src.film[0] if src.film else 0, height=src.film[1] if src.film else 0,
        max_depth=sec.get("max_depth", integer(1), 2),
        cameras=sec.get("cameras", lambda v, w: parse_cameras(v, w, src.up), []),
        emitters=[], objects=[], mitsuba=src)
    sec.done()
    return scene


def parse_scene(base: Path) -> Parser:
    def parse(value, where):
        sec = Section(value, where)
        if sec.has("mitsuba"):
            return parse_mitsuba_scene(sec, where, base)
        film = Section(sec.get("film", lambda v, _: v, {}), where.child("film"))
        width = film.get("width", integer(1, MAX_FILM), 128)
        height = film.get("height", integer(1, MAX_FILM), 128)
        film.done()
        scene = SceneConfig(
            width=width, height=height,
            max_depth=sec.get("max_depth", integer(1, MAX_DEPTH), 2),
            cameras=sec.get("cameras", parse_cameras, None),  # None: from optimize.target.dataset
            emitters=sec.get("emitters", list_of(parse_emitter(base)), []),
            objects=sec.get("objects", list_of(parse_object(base)), []),
        )
        sec.done()
        check_scene(scene, where.file)
        return scene
    return parse


def check_scene(scene: SceneConfig, file: str):
    """Unique object names and at most one environment emitter (also once an XML scene has been read)."""
    names = set()
    for obj in scene.objects:
        if obj.name in names:
            raise Where(file, obj.key + ".name").fail(f"duplicate object name '{obj.name}'")
        names.add(obj.name)
    n_env = sum(e.type in ("envmap", "sky", "constant") for e in scene.emitters)
    if n_env > 1:
        raise Where(file, "scene.emitters").fail("at most one environment emitter (envmap, sky or constant) is allowed")
