"""An experiment, whole when loaded: the file parsed and validated (:mod:`psdr_cli.config`),
then its scene read: a Mitsuba XML scene's cameras, film, emitters and objects filled in
(:mod:`psdr_cli.scene.mitsuba_xml`, one ``warn`` line per item psdr renders but cannot
differentiate), split OBJ objects expanded into their parts (:mod:`psdr_cli.scene.obj_parts`); then
the checks that need object names, views and emitters run. Loading activates the experiment's
Mitsuba variant (:func:`psdr_cli.support.backend.activate`): the commands, which all start from a loaded
experiment, do not activate it again (a Ray task, in its own process, does). A camera dataset
(``optimize.target.dataset``) gives the cameras and the film (:mod:`psdr_cli.experiment.dataset_frame`). Everything that uses an experiment
loads it here, so no later step has to ask whether its scene has been read.
"""
from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from ..config.experiment_file import Experiment, check_experiment, parse, read_file
from ..config.scene_section import check_scene
from ..errors import ConfigError
from ..scene import mitsuba_xml
from ..scene.mitsuba_xml import warn_stderr
from ..scene.obj_parts import expand_objects
from ..support import backend, fileio
from .dataset_frame import dataset_scene


def load_experiment(path, warn=warn_stderr) -> Experiment:
    """Read, validate and complete an experiment file (see the module docstring)."""
    return complete(read_file(path), warn)


def parse_experiment(data, file: Path, cwd: Path | None = None, warn=warn_stderr) -> Experiment:
    """An already-loaded YAML document as a complete experiment; ``file`` names the source in
    messages and anchors relative paths."""
    return complete(parse(data, file, cwd), warn)


def complete(exp: Experiment, warn=warn_stderr) -> Experiment:
    """``exp`` as parsed, with its Mitsuba variant activated (the one place an in-process command
    activates it: every command starts from a loaded experiment), its scene read and the checks
    that need object names run."""
    backend.activate(exp)
    scene = exp.scene
    if scene.mitsuba is None:
        scene = expand_objects(scene, str(exp.file))
    else:
        scene = mitsuba_xml.scene_config(exp, warn)
    check_scene(scene, str(exp.file))
    exp = replace(exp, scene=scene)
    if exp.optimize and exp.optimize.target_dataset:
        exp = dataset_scene(exp)
    check_experiment(exp)
    check_envmap_init(exp)
    return exp


def check_envmap_init(exp: Experiment):
    """The texels of ``optimize.envmap.init`` when it is an EXR file: readable, with R, G, B,
    finite and non-negative."""
    envmap = getattr(exp.optimize, "envmap", None) if exp.optimize else None
    path = envmap.init_file if envmap is not None else None
    if path is None:
        return
    where = "optimize.envmap.init"
    try:
        channels = fileio.read_exr(path)
    except Exception as exc:  # noqa: BLE001 - a damaged file
        raise ConfigError(exp.file, where, f"cannot read {path.name}: "
                          f"{str(exc).splitlines()[0] if str(exc) else type(exc).__name__}") from None
    if not all(c in channels for c in "RGB"):
        raise ConfigError(exp.file, where, f"{path.name} has no R, G, B channels")
    texels = np.stack([channels[c] for c in "RGB"], -1)
    if texels.size == 0:
        raise ConfigError(exp.file, where, f"{path.name} is empty")
    bad = int((~np.isfinite(texels)).sum())
    if bad:
        raise ConfigError(exp.file, where, f"{path.name} has {bad} NaN or infinite values")
    if texels.min() < 0:
        raise ConfigError(exp.file, where, f"{path.name} has negative radiance ({texels.min():g})")
