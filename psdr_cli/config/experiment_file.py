"""An experiment file: YAML parsed into an :class:`Experiment`, validated in one place.

Every problem is reported as one :class:`~psdr_cli.errors.ConfigError` line naming the file, the
key path and what was expected, e.g.
``bunny.yaml: scene.objects[1].bsdf.type: unknown 'difuse' (expected diffuse, roughconductor, ...)``.
Unknown keys are errors, so a typo never passes silently. The key reference is ``docs/config.md``.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import yaml

from ..errors import ConfigError
from .compare_section import CompareConfig, parse_compare
from .estimator_section import EstimatorConfig, parse_estimator
from .evaluate_section import EvaluateConfig, parse_evaluate
from .limits import check_paths
from .optimize_section import OptimizeConfig, parse_optimize
from .parameter import ParameterConfig, parse_parameter
from .scene_section import SceneConfig, parse_scene
from .unknowns import MATERIAL_UNKNOWNS
from .values import Section, Where, choice, integer, stage_count_error, string
from .vocabularies import VARIANTS


@dataclass
class Experiment:
    """A parsed experiment file. ``base_dir`` is the folder relative paths are resolved against."""
    file: Path
    name: str
    output: Path
    seed: int
    variant: str
    scene: SceneConfig
    parameter: ParameterConfig | None
    estimator: EstimatorConfig
    optimize: OptimizeConfig | None = None
    evaluate: EvaluateConfig | None = None
    compare: CompareConfig | None = None

    @property
    def base_dir(self) -> Path:
        return self.file.parent

    @property
    def run_dir(self) -> Path:
        return self.output / self.name

    def command_dir(self, command: str, out: Path | None = None) -> Path:
        """Output folder of a command: ``<output>/<name>/<command>`` (``out`` replaces ``output``;
        ``command`` one of :data:`COMMAND_FOLDERS`)."""
        return (Path(out).resolve() / self.name if out else self.run_dir) / command


def parse(data, file: Path, cwd: Path | None = None) -> Experiment:
    """Validate an already-loaded YAML document. ``file`` names the source in messages. The
    experiment as the file states it: its scene is read, and the checks that need object names
    run, by :func:`psdr_cli.experiment.load.parse_experiment`, which every user of an experiment loads with."""
    file = Path(file)
    where = Where(str(file), "")
    sec = Section(data, where)
    base = file.resolve().parent
    out = sec.get("output", string, "runs")
    name = sec.get("name", string, file.stem)
    scene = sec.get("scene", parse_scene(base))
    up = scene.mitsuba.up if scene.mitsuba else (0.0, 0.0, 1.0)
    exp = Experiment(
        file=file.resolve(),
        name=name,
        output=(Path(cwd or Path.cwd()) / out).resolve(),
        seed=sec.get("seed", integer(0), 0),
        variant=sec.get("variant", choice(*VARIANTS), "auto"),
        scene=scene,
        parameter=sec.get("parameter", lambda v, w: parse_parameter(v, w, up), None),
        estimator=sec.get("estimator", parse_estimator, EstimatorConfig()),
        optimize=sec.get("optimize", parse_optimize(base), None),
        evaluate=sec.get("evaluate", parse_evaluate(base), None),
        compare=sec.get("compare", parse_compare, None),
    )
    sec.done()
    check_camera_source(exp, data.get("scene"), where)
    if "/" in exp.name or exp.name in (".", ".."):
        raise where.child("name").fail(f"expected a plain folder name, got '{exp.name}'")
    return exp


def check_camera_source(exp: Experiment, scene_data, where: Where):
    """The cameras and film come from ``scene`` or, for a dataset, from its photographs: one or
    the other."""
    dataset = exp.optimize.target_dataset if exp.optimize else None
    if dataset is None:
        if exp.scene.cameras is None:
            raise where.child("scene").child("cameras").fail("missing (required)")
        return
    if exp.scene.mitsuba is not None:
        raise where.child("optimize").child("target").child("dataset").fail(
            "is not supported with an XML scene (scene.mitsuba) yet; describe the lights and the object in YAML")
    for key in ("cameras", "film"):
        if isinstance(scene_data, dict) and scene_data.get(key) is not None:
            raise where.child("scene").child(key).fail(
                "not allowed with optimize.target.dataset (the dataset's photographs give the cameras and the film)")


def check_stages(exp: Experiment):
    """The per-stage keys of ``optimize`` (``lambda``, ``downsample``) against the remesh schedule
    and the film: one value, or one per stage; each factor divides the film's width and height.
    Part of :func:`check_experiment`."""
    opt, where = exp.optimize, Where(str(exp.file), "optimize")
    stages = 1 + len(opt.remesh.at)
    for name, values in (("lambda", opt.lambda_), ("downsample", opt.downsample)):
        if len(values) not in (1, stages):
            raise stage_count_error(where.child(name), stages, len(values))
    for i, k in enumerate(opt.downsample):
        key = where.child("downsample")
        if exp.scene.width % k or exp.scene.height % k:
            raise (key.child(i) if len(opt.downsample) > 1 else key).fail(
                f"{k} does not divide the film's {exp.scene.width}×{exp.scene.height} pixels")


def check_experiment(exp: Experiment):
    """Checks that need the scene's object names, views and emitters. An XML scene or a split
    OBJ object is checked once it has been read (:func:`psdr_cli.experiment.load.parse_experiment`);
    ``optimize`` runs them again on the experiment it is given, which may have been changed in
    code after loading (another remesh schedule, another film: :func:`check_stages`)."""
    where = Where(str(exp.file), "")
    if not exp.scene.emitters and exp.scene.mitsuba is None:
        raise where.child("scene").child("emitters").fail(
            "expected at least 1 entry (a light; a camera dataset with optimize.envmap needs none: its unknown "
            "environment then starts from the photographs)")
    if exp.parameter and exp.parameter.object:
        names = [o.name for o in exp.scene.objects]
        if exp.parameter.object not in names:
            raise where.child("parameter").child("object").fail(
                f"unknown object '{exp.parameter.object}' (scene objects: {', '.join(names) or 'none'})")
    if exp.optimize:
        names = [o.name for o in exp.scene.objects]
        if exp.optimize.object not in names:
            raise where.child("optimize").child("object").fail(
                f"unknown object '{exp.optimize.object}' (scene objects: {', '.join(names) or 'none'})")
        bad = [v for v in exp.optimize.preview_views if v >= len(exp.scene.cameras)]
        if bad and not exp.optimize.target_images:
            raise where.child("optimize").child("preview_views").fail(
                f"view {bad[0]} does not exist (the scene has views 0..{len(exp.scene.cameras) - 1})")
        check_stages(exp)
        if exp.optimize.envmap_rotation and not any(e.type in ("envmap", "sky") for e in exp.scene.emitters):
            raise where.child("optimize").child("envmap_rotation").fail("needs an envmap or sky emitter")
        check_unknowns(exp, where.child("optimize"))
    if exp.parameter and exp.parameter.camera is not None and exp.parameter.camera >= len(exp.scene.cameras):
        raise where.child("parameter").child("camera").fail(
            f"camera {exp.parameter.camera} does not exist (the scene has cameras 0..{len(exp.scene.cameras) - 1})")
    for key, spp in (("estimator.spp", exp.estimator.spp), ("estimator.primary_spp", exp.estimator.primary_spp),
                     ("estimator.boundary_spp", exp.estimator.boundary_spp),
                     ("optimize.target.spp", exp.optimize.target_spp if exp.optimize else 0),
                     ("optimize.adjoint_spp", exp.optimize.adjoint_spp if exp.optimize else 0)):
        check_paths(spp, exp.scene.width, exp.scene.height, Where(str(exp.file), key).fail)
    if exp.parameter and exp.parameter.kind == "envmap_rotate":
        if not any(e.type in ("envmap", "sky") for e in exp.scene.emitters):
            raise where.child("parameter").child("kind").fail("'envmap_rotate' needs an envmap or sky emitter")


def check_unknowns(exp: Experiment, where: Where):
    """``optimize.envmap`` needs one ``envmap`` emitter of a YAML scene (its map is replaced) and
    excludes ``envmap_rotation``; ``optimize.material`` needs BSDF types that have the parameter."""
    o = exp.optimize
    if o.envmap is not None:
        w = where.child("envmap")
        if exp.scene.mitsuba is not None:
            raise w.fail("not available for a Mitsuba XML scene (give the scene's emitters in YAML)")
        if sum(e.type == "envmap" for e in exp.scene.emitters) != 1:
            raise w.fail("needs one emitter of type 'envmap' in scene.emitters (its map is replaced by the unknown; "
                         "a camera dataset needs none: its light then starts from the photographs)")
        if o.envmap_rotation:
            raise w.fail("excludes optimize.envmap_rotation (a free map holds its rotation)")
    if o.material and exp.scene.mitsuba is None:
        obj = next((x for x in exp.scene.objects if x.name == o.object), None)
        for m in o.material if obj is not None else ():
            types = MATERIAL_UNKNOWNS[m.name][1]
            if obj.bsdf.type not in types:
                raise where.child("material").child(m.name).fail(
                    f"the object's BSDF '{obj.bsdf.type}' has no {m.name} (use {' or '.join(types)})")


class UniqueKeyLoader(yaml.SafeLoader):
    """PyYAML's safe loader, except that a key given twice in one mapping is an error (PyYAML
    keeps the last value silently)."""

    def construct_mapping(self, node, deep=False):
        seen = {}
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=True)
            try:
                hash(key)
            except TypeError:
                continue  # the base class reports unhashable keys
            if key in seen:
                raise yaml.constructor.ConstructorError(
                    None, None, f"duplicate key '{key}' (first given on line {seen[key] + 1})", key_node.start_mark)
            seen[key] = key_node.start_mark.line
        return super().construct_mapping(node, deep)


UniqueKeyLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, UniqueKeyLoader.construct_mapping)


def read_file(path) -> Experiment:
    """Read and validate an experiment file, as :func:`parse` (its scene not yet read:
    :func:`psdr_cli.experiment.load.load_experiment` loads it whole)."""
    path = Path(path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise ConfigError(path, "", "file not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(path, "", f"cannot read: {exc}") from None
    try:
        data = yaml.load(text, Loader=UniqueKeyLoader)  # noqa: S506 - a SafeLoader subclass
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise ConfigError(path, where, f"invalid YAML: {problem}") from None
    if data is None:
        raise ConfigError(path, "", "the file is empty (expected a mapping with at least 'scene')")
    return parse(data, path)
