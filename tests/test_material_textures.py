"""optimize.material.NAME.texture: roughness and metallic recovered as bitmaps (issue: materials as
scalars or textures): texel gradients against finite differences, textures carried through a
remesh, written by the run and exported (glTF metallic-roughness texture, MTL map_Pr / map_Pm)."""
import json
import re

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest
import trimesh

from psdr_cli import cli, load_experiment
from psdr_cli.estimators.boundary_sampling import edge_list
from psdr_cli.estimators.passes import pass_seed
from psdr_cli.optimisation.problem import Problem, Shape
from psdr_cli.rendering.estimate import Settings
from psdr_cli.rendering.render import render_view
from psdr_cli.run_folder.state import State
from psdr_cli.scene import meshes
from psdr_cli.support import backend, fileio
from test_unknown_light import experiment_data, weighted_gradients, write


def test_material_texel_gradients_agree_with_finite_differences(tmp_path):
    """d/dt of a weighted image sum along a random ±1 direction of the texels of a 4 × 4 roughness
    and a 4 × 2 metallic texture on a principled UV sphere: reverse mode (interior + primary +
    direct, 12 passes at 8 spp) against central differences of the renderer (12 passes at 32 spp,
    common seeds for ±h), a z-test on the pass means with enough power (combined SE under 30 % of
    the derivative for roughness, 10 % for metallic)."""
    data = experiment_data(tmp_path, material={"roughness": {"texture": [4, 4]},
                                               "metallic": {"texture": [4, 2], "init": 0.3}})
    exp = load_experiment(write(tmp_path, data))
    backend.activate(exp)
    V, F, uv = meshes.uv_sphere(0.7, 16)
    problem = Problem(exp, Shape(V, F, uv), None, {})
    assert problem.opt["roughness"].shape == (4, 4, 1) and problem.opt["metallic"].shape == (2, 4, 1)
    settings = Settings.from_experiment(exp)
    edges = edge_list(problem.scene, exp.estimator, settings.edge_sort)
    rng = np.random.default_rng(0)
    weights = rng.random((16, 16, 3))
    direction = {k: rng.choice([-1.0, 1.0], size=problem.opt[k].shape) for k in ("roughness", "metallic")}
    x0 = {k: np.asarray(problem.opt[k]) for k in direction}
    n = 12

    def reverse(k):
        grads = weighted_gradients(problem, edges, exp, settings, weights, k)
        return {m: float((grads[m] * direction[m]).sum()) for m in direction}

    def weighted_sum(key, h, k):
        with dr.suspend_grad():
            problem.opt[key] = mi.TensorXf((x0[key] + h * direction[key]).astype(np.float32))
            problem.apply()
            img = render_view(problem.scene, 0, 32, seed=pass_seed(7, 0, k, 3))
            problem.opt[key] = mi.TensorXf(x0[key])
            problem.invalidate()
        return float((img * weights).sum())

    ad = [reverse(k) for k in range(n)]
    lines = []
    for key, h, power in (("roughness", 0.02, 0.3), ("metallic", 0.02, 0.1)):
        fd = [(weighted_sum(key, h, k) - weighted_sum(key, -h, k)) / (2 * h) for k in range(n)]
        a = np.array([g[key] for g in ad])
        ma, sa, mf, sf = a.mean(), a.std(ddof=1) / np.sqrt(n), np.mean(fd), np.std(fd, ddof=1) / np.sqrt(n)
        z = (ma - mf) / np.hypot(sa, sf)
        lines.append(f"{key}: AD {ma:.4g} ± {sa:.2g}, FD {mf:.4g} ± {sf:.2g}, z {z:.2f}")
        assert abs(z) < 3.5 and np.hypot(sa, sf) < power * abs(mf), lines
    print("\n".join(lines))
    problem.release()


def run_data(tmp_path):
    data = experiment_data(tmp_path, target={"spp": 16}, iterations=4, batch_size=1, learning_rate=0.001,
                           remesh={"method": "instant", "initial": 300, "at": [2], "vertices": [400]},
                           checkpoint_every=2,
                           material={"roughness": {"texture": [8, 4], "init": 0.6, "learning_rate": 0.05},
                                     "metallic": {"texture": [4, 4], "init": 0.2, "learning_rate": 0.05}})
    data["scene"]["cameras"] = [{"orbit": {"count": 3, "radius": 2.6, "elevation_deg": 20, "target": [0, 0, 0],
                                           "fov": 35}}]
    data["estimator"].update(spp=2, primary_spp=1, boundary_spp=1)
    return data


def test_material_textures_survive_a_remesh_and_are_exported(tmp_path, capsys):
    """4 iterations with a remesh at 2: both textures keep their size through the remesh (new
    atlas, texels transferred: they are no longer the uniform start), stay in their ranges, are
    written (roughness.exr, metallic.exr, named by optimize.json) and exported: the glTF's
    metallic-roughness texture holds them (G, B) at the mesh's UVs, the MTL names map_Pr / map_Pm."""
    path = write(tmp_path, run_data(tmp_path))
    assert cli.run(["optimize", str(path)]) == 0
    assert "transfer" not in capsys.readouterr().err
    run = tmp_path / "runs" / "light"
    state = State.load(run / "state.npz")
    rough, metal = state.values["roughness"], state.values["metallic"]
    assert rough.shape == (4, 8, 1) and metal.shape == (4, 4, 1) and state.uv is not None
    assert 0.01 <= rough.min() and rough.max() <= 1 and 0 <= metal.min() and metal.max() <= 1
    assert rough.std() > 1e-4 and metal.std() > 1e-4  # learnt, and carried through the remesh
    values = json.loads((run / "optimize.json").read_text())["values"]
    assert values["roughness"] == str(run / "roughness.exr") and values["metallic"] == str(run / "metallic.exr")
    assert np.allclose(fileio.read_rgb_exr(run / "roughness.exr")[..., 1], rough[..., 0], atol=1e-6)
    assert cli.run(["export", str(run)]) == 0
    out = run / "export"
    mtl = (out / "mesh.mtl").read_text()
    assert "map_Pr roughness.png" in mtl and "map_Pm metallic.png" in mtl
    glb = trimesh.load(out / "mesh.glb", force="mesh")
    material = glb.visual.material
    assert material.roughnessFactor == pytest.approx(1.0) and material.metallicFactor == pytest.approx(1.0)
    mr = np.asarray(material.metallicRoughnessTexture.convert("RGB"), np.float64) / 255
    assert mr.shape == (4, 8, 3)
    assert np.allclose(mr[..., 1], rough[..., 0], atol=0.5 / 255 + 1e-9)
    assert json.loads((out / "export.json").read_text())["roughness"] == "roughness.png"


@pytest.mark.parametrize("material, bsdf, message", [
    ({"roughness": {"texture": [0, 4]}}, None, r"optimize\.material\.roughness\.texture\[0\]: expected an integer"),
    ({"metallic": {"texture": [4]}}, None, r"optimize\.material\.metallic\.texture: expected \[width, height\]"),
    ({"roughness": {"texture": [4, 4]}}, {"type": "diffuse", "reflectance": 0.5},
     r"optimize\.material\.roughness: the object's BSDF 'diffuse' has no roughness"),
])
def test_bad_material_textures_are_one_line(tmp_path, capsys, material, bsdf, message):
    data = run_data(tmp_path)
    data["optimize"]["material"] = material
    if bsdf is not None:
        data["scene"]["objects"][0]["bsdf"] = bsdf
    capsys.readouterr()
    assert cli.run(["optimize", str(write(tmp_path, data))]) != 0
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(err) == 1 and re.search(message, err[0]), err
