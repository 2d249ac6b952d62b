"""Textures that survive remeshing and the export of a run (issue 39, items 3, 4, 6): after a
remesh the new mesh gets an xatlas atlas and the texture is transferred from the old surface by
closest points; ``psdr export`` writes OBJ + MTL + PNG and a binary glTF of a run or a mesh."""
import json
from dataclasses import replace

import mitsuba as mi
import numpy as np
import pytest
import yaml

from psdr_cli import atlas, backend, cli, fileio, load_experiment, meshes
from psdr_cli.config import OptimizeConfig
from psdr_cli.problem import texture_experiment
from psdr_cli.render import render_view
from psdr_cli.runs import read_log
from psdr_cli.scene import build_scene

# a 64 × 32 texture: 8 × 4 coloured cells (bilinear lookups blur only the cells' borders)
CELLS = np.random.default_rng(7).uniform(0.1, 0.9, (4, 8, 3))
TEXTURE = np.repeat(np.repeat(CELLS, 8, axis=0), 8, axis=1)


def scene_data(tmp_path, size=24):
    cams = [{"origin": [float(2.6 * np.cos(a)), float(2.6 * np.sin(a)), z], "target": [0, 0, 0], "fov": 35}
            for a, z in zip(np.radians([0, 90, 180, 270]), [1.5, -1.5, 1.5, -1.5])]
    return {"name": "tex", "output": str(tmp_path / "runs"), "seed": 1,
            "scene": {"film": {"width": size, "height": size}, "max_depth": 2, "cameras": cams,
                      "emitters": [{"type": "constant", "radiance": [1.0, 0.9, 0.8]}],
                      "objects": [{"name": "ball", "mesh": {"shape": "sphere", "radius": 0.8, "resolution": 12,
                                                            "uv": True},
                                   "bsdf": {"type": "diffuse", "reflectance": {"type": "bitmap", "file": "true.exr"}}}]},
            "estimator": {"spp": 4, "primary_spp": 4, "boundary_spp": 4, "terms": ["interior", "primary"]}}


def write(tmp_path, data, name="tex.yaml"):
    tmp_path.mkdir(parents=True, exist_ok=True)
    fileio.write_rgb_exr(tmp_path / "true.exr", TEXTURE)
    path = tmp_path / name
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def test_transferred_texture_renders_like_the_old_one(tmp_path):
    """The same shape, unwrapped anew by xatlas and its texture transferred from the UV sphere's
    layout: the renders of the two agree (mean |Δ| well below the contrast of the texture)."""
    path = write(tmp_path, scene_data(tmp_path, 32))
    exp = load_experiment(path)
    backend.activate(exp)
    V, F, uv = meshes.uv_sphere(0.8, 12)
    V2, F2, uv2 = atlas.unwrap(V, F, (64, 32))
    assert len(V2) > len(meshes.weld_vertices(V, F)[0])  # split at the new seams
    new = atlas.transfer((V, F, uv), V2, F2, uv2, TEXTURE)
    assert new.shape == TEXTURE.shape and np.isfinite(new).all()
    exp = replace(exp, optimize=OptimizeConfig(object="ball"))

    def render(mesh, texture):
        scene = build_scene(texture_experiment(exp, texture), objects={"ball": mesh})
        return np.concatenate([render_view(scene, v, 64, seed=3) for v in range(4)])
    before, after = render((V, F, uv), TEXTURE), render((V2, F2, uv2), new)
    grey = render((V, F, uv), np.full_like(TEXTURE, TEXTURE.mean()))
    diff, contrast = np.abs(after - before).mean(), np.abs(grey - before).mean()
    print(f"mean |render after - before| {diff:.4f}, against a grey texture {contrast:.4f}")
    assert diff < 0.2 * contrast, (diff, contrast)


def run_data(tmp_path, iterations):
    data = scene_data(tmp_path, 20)
    data["optimize"] = {"object": "ball", "target": {"spp": 32}, "iterations": iterations, "batch_size": 2,
                        "learning_rate": 0.002, "checkpoint_every": 4,
                        "init": {"mesh": {"shape": "sphere", "radius": 0.8, "resolution": 10, "uv": True}},
                        "remesh": {"method": "isotropic", "initial": 150, "at": [3], "vertices": [250]},
                        "albedo": {"texture": [32, 16], "learning_rate": 0.05}}
    return write(tmp_path, data), tmp_path / "runs" / "tex"


def test_textured_run_with_a_remesh_resumes_exactly(tmp_path):
    """A textured run remeshed at its start (remesh.initial) and at iteration 3 completes, with
    UVs split at the atlas's seams in its state; stopped at iteration 2 and resumed, it reproduces
    the uninterrupted run: losses, texture and final mesh."""
    full, run_full = run_data(tmp_path / "full", 5)
    assert cli.run(["optimize", str(full)]) == 0
    with np.load(run_full / "state.npz") as z:
        assert z["uv"].shape == (len(z["V"]), 2) and z["value_albedo"].shape == (16, 32, 3)
        assert len(z["V"]) > len(meshes.weld_vertices(z["V"], z["F"])[0])
    rows = read_log(run_full / "log.csv")
    assert int(rows[2]["vertices"]) != int(rows[3]["vertices"])  # remeshed at iteration 3
    part, run_part = run_data(tmp_path / "part", 5)
    assert cli.run(["optimize", str(part), "--iterations", "2"]) == 0
    assert cli.run(["optimize", str(part), "--resume"]) == 0
    assert [r["loss"] for r in read_log(run_part / "log.csv")] == [r["loss"] for r in rows]
    assert np.array_equal(fileio.read_rgb_exr(run_part / "albedo.exr"), fileio.read_rgb_exr(run_full / "albedo.exr"))
    assert (run_part / "final.ply").read_bytes() == (run_full / "final.ply").read_bytes()
