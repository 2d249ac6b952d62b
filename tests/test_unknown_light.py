"""The environment map and the material parameters as unknowns (issue 39, items 1 and 2):
``optimize.envmap`` (log-radiance texels, mean held, smoothness prior) and ``optimize.material``
(roughness, metallic, specular). Their reverse-mode gradients agree with central finite
differences, a stopped and resumed run reproduces the uninterrupted one, ``psdr export`` writes
them, ``psdr evaluate``'s held-out scenes apply a recovered map, and bad keys are one line each."""
import copy
import json
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest
import yaml

from conftest import bit_reproducible, write_raw_exr
from psdr_cli import api, cli, load_experiment
from psdr_cli.errors import PsdrError
from psdr_cli.estimators.boundary_sampling import edge_list
from psdr_cli.estimators.passes import pass_seed
from psdr_cli.scoring.held_out import apply_values
from psdr_cli.optimisation import photo_light
from psdr_cli.optimisation.problem import Problem, Shape
from psdr_cli.optimisation.unknowns.environment_map import solid_angle_weights
from psdr_cli.rendering.estimate import Settings, ad_image
from psdr_cli.rendering.render import render_view
from psdr_cli.run_folder.log import read_log
from psdr_cli.run_folder.state import State
from psdr_cli.scene.build import build_scene
from psdr_cli.support import backend, fileio
from psdr_cli.target_sources.camera_dataset import dataset_views
from psdr_cli.target_sources.source import TargetMasks

ROOT = Path(__file__).resolve().parents[1]

H, W = 8, 16
THETA = (np.arange(H)[:, None] + 0.5) / H * np.pi
PHI = (np.arange(W)[None, :] + 0.5) / W * 2 * np.pi


def lobe() -> np.ndarray:
    """(H, W) a bright lobe of the lat-long map, 1 at its centre."""
    d = np.stack([np.sin(THETA) * np.sin(PHI), np.cos(THETA) + 0 * PHI, -np.sin(THETA) * np.cos(PHI)], -1)
    axis = np.array([0.5, 0.75, 0.4]) / np.linalg.norm([0.5, 0.75, 0.4])
    return np.exp(-(np.arccos(np.clip(d @ axis, -1, 1)) / 0.35) ** 2)


def peaky_map() -> np.ndarray:
    """A dim sky with a bright lobe (the map's own importance sampling then matters: most of the
    lighting arrives through NEE samples of the lobe)."""
    return (0.1 + 20 * lobe())[..., None] * np.array([1.0, 0.9, 0.7])


def experiment_data(tmp_path, **optimize):
    fileio.write_rgb_exr(tmp_path / "env.exr", peaky_map().astype(np.float32))
    return {"name": "light", "output": str(tmp_path / "runs"), "seed": 1,
            "scene": {"film": {"width": 16, "height": 16}, "max_depth": 2,
                      "cameras": [{"origin": [0.5, -3, 1.2], "target": [0, 0, 0], "fov": 24}],
                      "emitters": [{"type": "envmap", "file": "env.exr"}],
                      "objects": [{"name": "ball", "mesh": {"shape": "sphere", "radius": 0.7, "subdivisions": 2},
                                   "bsdf": {"type": "principled", "base_color": 0.5, "roughness": 0.5,
                                            "metallic": 0.3}}]},
            "estimator": {"spp": 8, "primary_spp": 2, "boundary_spp": 2,
                          "terms": ["interior", "primary", "direct"]},
            "optimize": {"object": "ball", **optimize}}


def write(tmp_path, data, name="light.yaml"):
    path = tmp_path / name
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def weighted_gradients(problem, edges, exp, settings, weights, k: int) -> dict:
    """Reverse mode of pass ``k`` of view 0: d/dx Σ weights · image for every unknown x of the
    optimiser (numpy), the gradients cleared afterwards."""
    problem.apply()
    img = ad_image(problem.scene, edges, 0, exp.estimator.terms, settings, pass_index=k)
    dr.backward(dr.sum(img * mi.Float(weights.ravel().astype(np.float32))))
    problem.invalidate()
    grads = {key: np.asarray(dr.grad(problem.opt[key])) for key in problem.opt.keys()}
    for key in problem.opt.keys():
        dr.set_grad(problem.opt[key], 0.0)
    return grads


def test_envmap_and_material_gradients_agree_with_finite_differences(tmp_path):
    """d/dt of a weighted image sum along a direction of all log-texels (the bright lobe and a
    smooth longitude wave), and w.r.t. roughness, metallic and specular of a principled sphere:
    reverse mode (interior + primary + direct, 12 independent passes at 8 spp) against central
    differences of the renderer (12 passes at 32 spp, common seeds for ±h), a z-test on the pass
    means, and enough power (the combined SE under 10 % of the derivative, 30 % for the noisier
    roughness). Measured: texels 24.93 ± 0.20 vs 25.11 ± 0.14 (z −0.72; without Le attached in
    NEE 4.36 ± 0.10, z −120); roughness 10.1 ± 1.8 vs 12.1 ± 1.5 (z −0.83); metallic −85.4 ± 0.7 vs
    −84.0 ± 0.5 (z −1.59); specular 12.44 ± 0.10 vs 12.50 ± 0.06 (z −0.52)."""
    data = experiment_data(tmp_path, envmap={"resolution": [W, H], "init": "env.exr"},
                           material={"roughness": {}, "metallic": {}, "specular": {}})
    exp = load_experiment(write(tmp_path, data))
    backend.activate(exp)
    built = build_scene(exp).objects["ball"]
    problem = Problem(exp, Shape(built.vertices, built.faces), None, {})
    assert np.allclose(np.exp(np.asarray(problem.opt["envmap"])), peaky_map(), rtol=1e-5)
    settings = Settings.from_experiment(exp)
    edges = edge_list(problem.scene, exp.estimator, settings.edge_sort)
    weights = np.random.default_rng(0).random((16, 16, 3))
    direction = (lobe() + 0.3 * np.sin(THETA) * np.cos(PHI))[..., None] * np.array([1.0, 0.5, -0.5])
    x0 = {k: np.asarray(problem.opt[k]) for k in problem.opt.keys()}
    names = ("roughness", "metallic", "specular")
    n = 12

    def reverse(k):
        grads = weighted_gradients(problem, edges, exp, settings, weights, k)
        out = {"envmap": float((grads["envmap"] * direction).sum())}
        out.update({m: float(grads[m].ravel()[0]) for m in names})
        return out

    def weighted_sum(key, h, k):
        with dr.suspend_grad():
            if key == "envmap":
                problem.opt["envmap"] = mi.TensorXf((x0["envmap"] + h * direction).astype(np.float32))
            else:
                problem.opt[key] = mi.Float(float(x0[key][0] + h))
            problem.apply()
            img = render_view(problem.scene, 0, 32, seed=pass_seed(7, 0, k, 3))
            problem.opt[key] = type(problem.opt[key])(x0[key])
            problem.invalidate()
        return float((img * weights).sum())

    ad = [reverse(k) for k in range(n)]
    lines = []
    for key, h in (("envmap", 0.05), ("roughness", 0.02), ("metallic", 0.02), ("specular", 0.02)):
        fd = [(weighted_sum(key, h, k) - weighted_sum(key, -h, k)) / (2 * h) for k in range(n)]
        a = np.array([g[key] for g in ad])
        ma, sa, mf, sf = a.mean(), a.std(ddof=1) / np.sqrt(n), np.mean(fd), np.std(fd, ddof=1) / np.sqrt(n)
        z = (ma - mf) / np.hypot(sa, sf)
        lines.append(f"{key}: AD {ma:.4g} ± {sa:.2g}, FD {mf:.4g} ± {sf:.2g}, z {z:.2f}")
        assert abs(z) < 3.5 and np.hypot(sa, sf) < (0.3 if key == "roughness" else 0.1) * abs(mf), lines
    print("\n".join(lines))
    problem.release()


def run_data(tmp_path, iterations=4):
    data = experiment_data(tmp_path, target={"spp": 16}, iterations=iterations, batch_size=1, learning_rate=0.001,
                           remesh={"method": "none"}, checkpoint_every=2, albedo={"init": 0.4},
                           envmap={"resolution": [8, 4], "init": 0.5, "smoothness": 0.1, "learning_rate": 0.1},
                           material={"roughness": {"init": 0.6}, "metallic": {"init": 0.02, "learning_rate": 0.05}})
    data["scene"]["cameras"] = [{"orbit": {"count": 3, "radius": 2.6, "elevation_deg": 20, "target": [0, 0, 0],
                                           "fov": 35}}]
    data["estimator"].update(spp=2, primary_spp=1, boundary_spp=1)
    return data


@pytest.fixture(scope="module")
def light_runs(tmp_path_factory):
    """(run folder of 4 iterations at once, run folder of 2 then --resume) of :func:`run_data`."""
    tmp = tmp_path_factory.mktemp("light")
    (tmp / "full").mkdir()
    (tmp / "part").mkdir()
    full = write(tmp / "full", run_data(tmp / "full"))
    part = write(tmp / "part", run_data(tmp / "part"))
    assert cli.run(["optimize", str(full)]) == 0
    assert cli.run(["optimize", str(part), "--iterations", "2"]) == 0
    assert cli.run(["optimize", str(part), "--resume"]) == 0
    return tmp / "full" / "runs" / "light", tmp / "part" / "runs" / "light"


@bit_reproducible
def test_stopped_and_resumed_run_reproduces_the_uninterrupted_one(light_runs):
    """4 iterations at once, and 2 then --resume: the same losses, unknowns and Adam moments."""
    run_full, run_part = light_runs
    assert [r["loss"] for r in read_log(run_part / "log.csv")] == [r["loss"] for r in read_log(run_full / "log.csv")]
    a, b = State.load(run_full / "state.npz"), State.load(run_part / "state.npz")
    assert set(a.values) == {"albedo", "envmap_log", "roughness", "metallic"}
    for k in a.values:
        assert np.array_equal(a.values[k], b.values[k]), k
    for k in a.adam:
        assert all(np.array_equal(x, y) for x, y in zip(a.adam[k][1:], b.adam[k][1:])), k


def test_a_run_with_unknown_light_and_materials_keeps_their_ranges_and_exports(light_runs):
    """The environment's solid-angle mean stays at its initial 0.5 (albedo is free too); metallic
    stays in [0, 1] (it starts at 0.02 with a large step); optimize.json names envmap.exr and holds
    the materials; psdr export writes environment.exr and the glTF factors."""
    run_full, _ = light_runs
    a = State.load(run_full / "state.npz")
    env = fileio.read_rgb_exr(run_full / "envmap.exr")
    w = np.sin((np.arange(4) + 0.5) / 4 * np.pi)[:, None, None]
    assert env.shape == (4, 8, 3) and (env * w).sum() / (w.sum() * 8 * 3) == pytest.approx(0.5, rel=1e-5)
    assert np.allclose(env, np.exp(a.values["envmap_log"]), rtol=1e-6) and env.std() > 0
    values = json.loads((run_full / "optimize.json").read_text())["values"]
    assert values["envmap"] == str(run_full / "envmap.exr")
    assert 0.01 <= values["roughness"][0] <= 1 and 0 <= values["metallic"][0] <= 1
    assert cli.run(["export", str(run_full)]) == 0
    out = run_full / "export"
    assert np.allclose(fileio.read_rgb_exr(out / "environment.exr"), env, rtol=1e-6)
    record = json.loads((out / "export.json").read_text())
    assert record["roughness"] == pytest.approx(values["roughness"][0])
    import trimesh  # noqa: PLC0415
    glb = trimesh.load(out / "mesh.glb", force="mesh")
    material = glb.visual.material
    assert material.roughnessFactor == pytest.approx(values["roughness"][0], abs=1e-6)
    assert material.metallicFactor == pytest.approx(values["metallic"][0], abs=1e-6)


def psdr(capsys, *args):
    capsys.readouterr()
    code = cli.run([str(a) for a in args])
    return code, [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]


def test_bad_unknown_keys_are_one_line(tmp_path, capsys):
    """A zero resolution, a non-finite or negative texel in an init file, a non-positive constant,
    a scene without an envmap emitter, envmap with envmap_rotation, a material the BSDF does not
    have, a roughness out of range: one line each, exit 2."""
    backend.activate(load_experiment(write(tmp_path, run_data(tmp_path, iterations=1))))
    write_raw_exr(tmp_path / "nan.exr", np.full((4, 8, 3), np.nan, np.float32))
    fileio.write_rgb_exr(tmp_path / "neg.exr", np.full((4, 8, 3), -1.0, np.float32))
    base = run_data(tmp_path, iterations=1)
    sky = [{"type": "sky", "sun_direction": [0, 0, 1]}]
    cases = [({"envmap": {"resolution": [0, 4]}}, None, "expected an integer >= 2"),
             ({"envmap": {"init": "nan.exr"}}, None, "NaN or infinite values"),
             ({"envmap": {"init": "neg.exr"}}, None, "negative radiance"),
             ({"envmap": {"init": 0}}, None, "expected a radiance > 0"),
             ({"envmap": {"mean": "maybe"}}, None, "unknown 'maybe'"),
             ({"envmap": {}}, sky, "needs one emitter of type 'envmap'"),
             ({"envmap": {}, "envmap_rotation": {}}, None, "excludes optimize.envmap_rotation"),
             ({"material": {"roughness": {"init": 1.5}}}, None, "expected a number <= 1.0"),
             ({"material": {"shininess": {}}}, None, "unknown key"),
             ({"material": {}}, None, "expected at least one of"),
             ({"material": {"metallic": {}}}, "diffuse", "has no metallic")]
    for change, scene, expected in cases:
        data = copy.deepcopy(base)
        data["optimize"].pop("envmap"), data["optimize"].pop("material")
        data["optimize"].update(change)
        if scene == "diffuse":
            data["scene"]["objects"][0]["bsdf"] = {"type": "diffuse", "reflectance": 0.5}
        elif scene is not None:
            data["scene"]["emitters"] = scene
        code, err = psdr(capsys, "optimize", write(tmp_path, data))
        assert code == 2 and len(err) == 1 and expected in err[0], (change, err)


def test_held_out_scenes_apply_the_recovered_environment_map(tmp_path):
    """held_out.apply_values with a run's ``envmap`` (an 8 × 4 map, as envmap.exr holds it) sets
    the emitter's texels: the scene then renders exactly as one built with that map as its file
    (the emitter's scale 1.5 and rotation kept); an unreadable map is one PsdrError line."""
    small = (0.05 + np.linspace(0, 2, 8)[None, :, None] * np.linspace(1, 0.2, 4)[:, None, None]
             * np.array([1.0, 0.6, 0.3])).astype(np.float32)
    fileio.write_rgb_exr(tmp_path / "envmap.exr", small)
    data = experiment_data(tmp_path)
    data["scene"]["emitters"][0].update(scale=1.5, rotate_deg=30)
    recovered = load_experiment(write(tmp_path, data))
    backend.activate(recovered)
    scene = build_scene(recovered)
    apply_values(scene, recovered, {"envmap": str(tmp_path / "envmap.exr")})
    data["scene"]["emitters"][0]["file"] = "envmap.exr"
    direct = build_scene(load_experiment(write(tmp_path, data, "direct.yaml")))
    a, b = render_view(scene, 0, 16, seed=3), render_view(direct, 0, 16, seed=3)
    assert np.abs(a - render_view(build_scene(recovered), 0, 16, seed=3)).max() > 0.05  # the map matters
    assert np.allclose(a, b, rtol=1e-5, atol=1e-6)
    (tmp_path / "bad.exr").write_text("not an image")
    with pytest.raises(PsdrError, match="cannot read the recovered environment map"):
        apply_values(scene, recovered, {"envmap": str(tmp_path / "bad.exr")})


def test_held_out_scenes_apply_the_recovered_materials(tmp_path):
    """held_out.apply_values with recovered roughness, metallic and specular numbers: the scene
    renders exactly as one built with those values in the object's principled BSDF (and unlike
    the scene as given)."""
    data = experiment_data(tmp_path)
    recovered = load_experiment(write(tmp_path, data))
    backend.activate(recovered)
    scene = build_scene(recovered)
    apply_values(scene, recovered, {"roughness": [0.2], "metallic": [0.8], "specular": [0.1]})
    data["scene"]["objects"][0]["bsdf"].update(roughness=0.2, metallic=0.8, specular=0.1)
    direct = build_scene(load_experiment(write(tmp_path, data, "direct.yaml")))
    a, b = render_view(scene, 0, 16, seed=3), render_view(direct, 0, 16, seed=3)
    assert np.abs(a - render_view(build_scene(recovered), 0, 16, seed=3)).max() > 0.05
    assert np.allclose(a, b, rtol=1e-5, atol=1e-6)


# --------------------------------------------------------------------------------------------
# A capture without a light probe (psdr_cli/optimisation/photo_light.py)
# --------------------------------------------------------------------------------------------
def test_photograph_brightness_is_the_straight_mean_inside_the_masks():
    """B = Σ T / Σ α over premultiplied targets: a half-covered view of colour c gives c."""
    alpha = np.zeros((4, 4))
    alpha[:, :2] = 1.0
    alpha[0, 2] = 0.5
    colour = np.array([0.2, 0.4, 0.8])
    target = alpha[..., None] * colour
    got = photo_light.photograph_brightness([target, target], TargetMasks([alpha, alpha]))
    np.testing.assert_allclose(got, colour, rtol=1e-12)
    np.testing.assert_allclose(photo_light.photograph_brightness([np.ones((2, 2, 3))], None), 1.0)
    photo = np.broadcast_to(colour, (4, 4, 3)) * 1.0  # the background visible: C everywhere, masks apart
    photo[:, 2:] = [0.9, 0.9, 0.9]
    photo[0, 2] = colour
    got = photo_light.photograph_brightness([photo], TargetMasks([alpha]), premultiplied=False)
    np.testing.assert_allclose(got, colour, rtol=1e-12)


def test_a_capture_without_a_light_probe_starts_from_its_photographs(tmp_path):
    """The example capture with no emitter at all and the environment unknown: the run gets an
    environment whose start L_0 = B / a reproduces the photographs' mean brightness with the
    starting albedo a = 0.5, held at that mean (mean: auto with the albedo unknown); the same
    experiment outside a camera dataset is refused in one line."""
    data = yaml.safe_load((ROOT / "configs" / "photos" / "bunny_blender.yaml").read_text())
    data.update(output=str(tmp_path / "runs"), name="noprobe")
    data["scene"]["emitters"] = []
    data["optimize"]["target"]["dataset"] = {"path": str(ROOT / "data" / "photo_bunny" / "blender")}
    data["optimize"].update(iterations=3, batch_size=2, checkpoint_every=3, preview_views=[0], cameras="off",
                            remesh={"method": "none"}, envmap={"resolution": [16, 8]}, albedo={"init": 0.5})
    path = tmp_path / "noprobe.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    exp = load_experiment(path)
    assert [e.type for e in exp.scene.emitters] == ["envmap"] and exp.scene.emitters[0].file is None
    result = api.optimize(exp, warn=lambda m: None)
    assert result.iterations == 3
    views = dataset_views(exp)
    premultiplied = [v.image * v.mask[..., None] for v in views]
    expected = photo_light.photograph_brightness(premultiplied, TargetMasks([v.mask for v in views])) / 0.5
    texels = np.asarray(fileio.read_rgb_exr(exp.run_dir / "envmap.exr"), np.float64)
    w = solid_angle_weights(*texels.shape[:2])[..., None]
    mean = (texels * w).sum((0, 1)) / w.sum()
    np.testing.assert_allclose(mean.mean(), expected.mean(), rtol=1e-3)  # the map's mean is held at L_0
    assert 0.5 < expected.mean() < 3  # a studio map × 0.8 on a 0.6-albedo bunny: B ≈ 0.5, L_0 ≈ 1
    data["optimize"]["target"] = {"mesh": {"shape": "sphere"}}
    data["scene"]["cameras"] = [{"origin": [0, -3, 1], "target": [0, 0, 0]}]
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    with pytest.raises(PsdrError) as err:
        load_experiment(path)
    assert "needs none" in str(err.value) and "\n" not in str(err.value), err.value
