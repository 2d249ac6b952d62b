"""The unknowns as an extension point (psdr_cli/optimisation/unknowns): an unknown added the
README's way, its module (here a class in this file) plus its name in the registry, is made by the
problem, written into the scene, optimised, checkpointed, saved and resumed, with no other module
changed. The throwaway is a global light scale s: the constant emitter's radiance becomes s · L."""
from __future__ import annotations

import copy
import json

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest
import yaml

from psdr_cli.commands.optimize import optimize
from psdr_cli.config.scene_ids import emitter_id
from psdr_cli.experiment.load import load_experiment
from psdr_cli.optimisation.unknowns import registry
from psdr_cli.optimisation.unknowns.unknown import Saved, Start, Unknown, detached
from psdr_cli.run_folder.checkpoints import Picture
from psdr_cli.run_folder.state import State
from psdr_cli.support import fileio

#: A light scale starts here; the targets are rendered at s = 1.
START = 0.5


class LightScale(Unknown):
    """The throwaway unknown: s, Adam entry and saved value ``light_scale``; the scene's first
    emitter's radiance s · L (L as the scene was built); its checkpoint file ``light_scale.exr``
    (one texel, s in every channel) and its ``optimize.json`` entry."""
    name = "light_scale"

    @staticmethod
    def wanted(cfg) -> bool:
        return True

    def __init__(self, start: Start):
        super().__init__(start)
        self.key = f"{emitter_id(0)}.radiance.value"
        self.initial = mi.Color3f(start.params[self.key])
        saved = start.values.get("light_scale")
        start.opt["light_scale"] = mi.Float(START if saved is None else float(saved[0]))
        start.opt.set_learning_rate({"light_scale": 0.05})

    def entries(self) -> dict:
        return {"light_scale": (self.start.opt, "light_scale")}

    def scene_values(self) -> dict:
        return {self.key: self.initial * self.start.opt["light_scale"]}

    def write_saved(self, saved: Saved):
        if "light_scale" in saved.values:
            self.start.params[self.key] = self.initial * float(saved.values["light_scale"][0])

    def values(self) -> dict:
        return {"light_scale": np.asarray(self.start.opt["light_scale"], np.float64).ravel()}

    def checkpoint_files(self, files, iteration: int) -> list:
        return [Picture(files.root / "light_scale.exr", np.full((1, 1, 3), self.values()["light_scale"][0]), png=False)]

    def summary(self, files) -> dict:
        return {"light_scale": self.values()["light_scale"].tolist()}

    def detach(self):
        detached(self.start.params, self.key)


def with_light_scale(monkeypatch):
    """The registry with the throwaway added after the others, as a module named in NAMES adds it."""
    monkeypatch.setattr(registry, "NAMES", registry.NAMES + (LightScale.name,))
    monkeypatch.setattr(registry, "UNKNOWNS", registry.UNKNOWNS + (LightScale,))


EXPERIMENT = {
    "name": "scale", "seed": 4,
    "scene": {"film": {"width": 16, "height": 16}, "max_depth": 2,
              "cameras": [{"orbit": {"count": 3, "radius": 2.6, "elevation_deg": 20, "target": [0, 0, 0], "fov": 30}}],
              "emitters": [{"type": "constant", "radiance": [1.0, 0.9, 0.8]}],
              "objects": [{"name": "ball", "mesh": {"shape": "sphere", "radius": 0.6, "subdivisions": 2},
                           "bsdf": {"type": "diffuse", "reflectance": 0.6}}]},
    "estimator": {"spp": 2, "primary_spp": 1, "boundary_spp": 1, "terms": ["interior", "primary"]},
    "optimize": {"object": "ball", "target": {"spp": 16}, "iterations": 6, "batch_size": 2,
                 "learning_rate": 0.001, "checkpoint_every": 3, "preview_views": [0],
                 "remesh": {"method": "none"}},
}


def experiment(folder):
    data = copy.deepcopy(EXPERIMENT)
    data["output"] = str(folder / "runs")
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "scale.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return load_experiment(path)


def test_an_unknown_added_the_readme_way_is_optimised_checkpointed_and_resumed(tmp_path, monkeypatch):
    """With the throwaway registered: s moves from its start towards the targets' 1 (the renders
    are too dark), its checkpoint file holds s at that checkpoint, optimize.json and state.npz
    hold it with its Adam moments, and a run stopped after 3 iterations and resumed ends where the
    uninterrupted run ends, bit for bit (s, its moments and the shape restored). Without the
    registration line none of it exists."""
    plain = experiment(tmp_path / "plain")
    optimize(plain, iterations=2, warn=lambda m: None)
    assert "light_scale" not in State.load(plain.run_dir / "state.npz").values
    with_light_scale(monkeypatch)
    whole, parts = experiment(tmp_path / "whole"), experiment(tmp_path / "parts")
    optimize(whole, warn=lambda m: None)
    optimize(parts, iterations=3, warn=lambda m: None)
    at_three = fileio.read_rgb_exr(parts.run_dir / "light_scale.exr")
    resumed = optimize(parts, resume=True, warn=lambda m: None)
    assert resumed.resumed_from == 3
    a, b = State.load(whole.run_dir / "state.npz"), State.load(parts.run_dir / "state.npz")
    s = float(a.values["light_scale"][0])
    assert START + 0.1 < s < 1.2, s
    print(f"light scale {START} → {s:.4f} in 6 steps")
    assert a.adam["light_scale"][0] == 6  # six Adam steps, across the resume
    assert np.array_equal(a.values["light_scale"], b.values["light_scale"])
    assert all(np.array_equal(x, y) for x, y in zip(a.adam["light_scale"][1:], b.adam["light_scale"][1:]))
    assert np.array_equal(a.V, b.V)
    written = fileio.read_rgb_exr(whole.run_dir / "light_scale.exr")
    assert np.allclose(written, s) and START < float(at_three[0, 0, 0]) < s
    assert json.loads((whole.run_dir / "optimize.json").read_text())["values"]["light_scale"] == pytest.approx([s])
