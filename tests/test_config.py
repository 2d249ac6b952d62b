"""Experiment-file parsing: defaults, typed values, camera rings, cross-checks."""
import math

import pytest

from psdr_cli.config.cameras_section import orbit_cameras
from psdr_cli.config.vocabularies import TERMS
from psdr_cli.errors import ConfigError
from psdr_cli.experiment.load import load_experiment, parse_experiment

from conftest import experiment


def parse(d, tmp_path):
    return parse_experiment(d, tmp_path / "exp.yaml", cwd=tmp_path)


def test_full_experiment_parses_with_defaults(tmp_path):
    exp = parse(experiment(), tmp_path)
    assert exp.name == "t" and exp.seed == 1 and exp.variant == "auto"
    assert exp.run_dir == tmp_path / "out" / "t"
    sc = exp.scene
    assert (sc.width, sc.height, sc.max_depth) == (24, 16, 2)
    assert sc.cameras[0].up == (0.0, 0.0, 1.0) and sc.cameras[0].fov == 40
    area = sc.emitters[0]
    assert area.type == "area" and area.radiance == (10.0, 10.0, 10.0) and area.size == (1.0, 1.0)
    ball, floor = sc.objects
    assert ball.mesh.shape == "sphere" and ball.mesh.params == {"radius": 0.4, "subdivisions": 2}
    assert ball.transform.translate == (0.0, 0.0, 0.5) and ball.edges and not floor.edges
    assert ball.bsdf.type == "diffuse" and ball.bsdf.params["reflectance"] == (0.7, 0.5, 0.3)
    assert floor.mesh.params["size"] == (4.0, 4.0)
    assert exp.parameter is None
    est = exp.estimator
    assert est.spp == 4 and est.terms == TERMS and est.sampling == "mis" and est.guiding == "auto"


def test_name_defaults_to_file_stem_and_output_to_runs(tmp_path):
    d = experiment()
    del d["name"], d["output"]
    exp = parse_experiment(d, tmp_path / "bunny_rot.yaml", cwd=tmp_path)
    assert exp.name == "bunny_rot" and exp.output == tmp_path / "runs"


def test_mesh_file_is_relative_to_the_yaml_file(tmp_path):
    d = experiment()
    d["scene"]["objects"][0]["mesh"] = {"file": "meshes/a.ply"}
    exp = parse_experiment(d, tmp_path / "sub" / "exp.yaml", cwd=tmp_path)
    assert exp.scene.objects[0].mesh.file == (tmp_path / "sub" / "meshes" / "a.ply").resolve()


def test_cameras_may_be_a_single_orbit_mapping(tmp_path):
    """``cameras: {orbit: {...}}`` (no list) is the same ring as ``cameras: [{orbit: {...}}]``."""
    ring = {"count": 3, "radius": 2, "elevation_deg": 20, "target": [0, 0, 0]}
    a, b = experiment(), experiment()
    a["scene"]["cameras"] = {"orbit": dict(ring)}
    b["scene"]["cameras"] = [{"orbit": dict(ring)}]
    assert parse(a, tmp_path).scene.cameras == parse(b, tmp_path).scene.cameras
    a["scene"]["cameras"] = {"orbit": dict(ring), "origin": [0, 1, 0]}
    with pytest.raises(ConfigError, match=r"scene\.cameras: expected a list"):
        parse(a, tmp_path)


def test_optimize_target_object_is_an_alias_of_optimize_object(tmp_path):
    d = experiment()
    d["optimize"] = {"target": {"object": "ball"}}
    assert parse(d, tmp_path).optimize.object == "ball"
    d["optimize"] = {"object": "ball", "target": {"object": "ball", "spp": 8}}
    assert parse(d, tmp_path).optimize.object == "ball"
    d["optimize"] = {"object": "ball", "target": {"object": "floor"}}
    with pytest.raises(ConfigError, match=r"optimize\.target\.object: 'floor' contradicts"):
        parse(d, tmp_path)
    d["optimize"] = {"target": {"spp": 8}}
    with pytest.raises(ConfigError, match=r"optimize\.object: missing"):
        parse(d, tmp_path)


def test_orbit_expands_to_a_ring_of_cameras(tmp_path):
    d = experiment()
    d["scene"]["cameras"] = [{"orbit": {"count": 6, "radius": 2, "elevation_deg": 30, "azimuth_deg": 10,
                                        "target": [0, 0, 1], "fov": 35}},
                             {"origin": [0, -1, 0], "target": [0, 0, 0]}]
    cams = parse(d, tmp_path).scene.cameras
    assert len(cams) == 7
    for i, c in enumerate(cams[:6]):
        rel = [o - t for o, t in zip(c.origin, c.target)]
        assert math.dist(c.origin, c.target) == pytest.approx(2)
        assert math.degrees(math.asin(rel[2] / 2)) == pytest.approx(30)
        assert math.degrees(math.atan2(rel[1], rel[0])) % 360 == pytest.approx((10 + 60 * i) % 360)
        assert c.fov == 35
    assert cams[6].fov == 40


def test_orbit_around_another_up_axis_keeps_radius_and_elevation():
    cams = orbit_cameras(4, 3.0, 20.0, 0.0, (1, 2, 3), 40, up=(0, 1, 0))
    for c in cams:
        rel = [o - t for o, t in zip(c.origin, c.target)]
        assert math.hypot(*rel) == pytest.approx(3.0)
        assert rel[1] / 3.0 == pytest.approx(math.sin(math.radians(20)))


def test_terms_accept_a_comma_string_and_keep_canonical_order(tmp_path):
    exp = parse(experiment(estimator={"terms": "direct, primary"}), tmp_path)
    assert exp.estimator.terms == ("primary", "direct")


def test_parameter_and_guiding_sections(tmp_path):
    exp = parse(experiment(parameter={"object": "ball", "kind": "translate", "axis": [0, 0, 2]},
                           estimator={"guiding": "kdtree", "kdtree": {"samples_per_node": 64},
                                      "grid": {"resolution": [8, 4, 4]}, "edge_sort": True}), tmp_path)
    assert exp.parameter.axis == (0.0, 0.0, 1.0)  # normalised
    assert exp.estimator.kdtree.samples_per_node == 64 and exp.estimator.kdtree.max_depth == 24
    assert exp.estimator.grid.resolution == (8, 4, 4) and exp.estimator.edge_sort


def test_guiding_auto_parses_and_is_the_default(tmp_path):
    exp = parse(experiment(estimator={"guiding": "auto", "kdtree": {"initial_samples": 0, "refine_ratio": 1.5}}),
                tmp_path)
    assert exp.estimator.guiding == "auto" and exp.estimator.kdtree.refine_ratio == 1.5
    assert parse(experiment(), tmp_path).estimator.guiding == "auto"
    with pytest.raises(ConfigError, match="guiding"):
        parse(experiment(estimator={"guiding": "automatic"}), tmp_path)


def test_every_emitter_type(tmp_path):
    d = experiment()
    d["scene"]["emitters"] = [
        {"type": "sky", "sun_direction": [0, 1, 1], "turbidity": 4},
        {"type": "area", "center": [0, 0, 2], "normal": [0, 0, -3], "size": [1, 2], "radiance": [1, 2, 3]}]
    ems = parse(d, tmp_path).scene.emitters
    assert ems[0].sun_direction == pytest.approx((0, 2 ** -0.5, 2 ** -0.5)) and ems[0].turbidity == 4
    assert ems[1].normal == (0.0, 0.0, -1.0) and ems[1].radiance == (1.0, 2.0, 3.0)


@pytest.mark.parametrize("mutate, key, words", [
    (lambda d: d["scene"]["film"].update(width=0), "scene.film.width", "integer >= 1"),
    (lambda d: d["scene"]["objects"][0]["bsdf"].update(type="difuse"), "scene.objects[0].bsdf.type",
     "unknown 'difuse' (expected diffuse, roughconductor"),
    (lambda d: d["scene"]["objects"][0]["bsdf"].update(reflectanse=1), "scene.objects[0].bsdf.reflectanse",
     "unknown key"),
    (lambda d: d["scene"]["objects"][1].update(name="ball"), "scene.objects[1].name", "duplicate"),
    (lambda d: d["scene"]["emitters"].append({"type": "constant", "radiance": 1}) or
     d["scene"]["emitters"].append({"type": "sky", "sun_direction": [0, 0, 1]}), "scene.emitters",
     "at most one environment"),
    (lambda d: d["scene"].update(cameras=[]), "scene.cameras", "at least 1"),
    (lambda d: d["scene"]["cameras"][0].update(up=[0, 6, -3.4]), "scene.cameras[0]", "parallel"),
    (lambda d: d.update(parameter={"kind": "envmap_rotate"}), "parameter.kind", "needs an envmap"),
    (lambda d: d.update(parameter={"kind": "translate"}), "parameter.object", "missing"),
    (lambda d: d.update(estimator={"terms": ["direct", "primery"]}), "estimator.terms[1]", "unknown 'primery'"),
    (lambda d: d.update(estimator={"grid": {"resolution": [4, 4]}}), "estimator.grid.resolution", "3 integers"),
    (lambda d: d["scene"]["objects"][0]["mesh"].update(file="x.ply"), "scene.objects[0].mesh", "not both"),
    (lambda d: d.update(estimator={"engine": "mitsuba3"}), "estimator.engine", "unknown 'mitsuba3' (expected psdr, mitsuba)"),
    (lambda d: d.update(estimator={"engine": "mitsuba", "mitsuba_integrator": "prb"}), "estimator.mitsuba_integrator",
     "expected direct_projective, prb_projective"),
    (lambda d: d.update(estimator={"mitsuba_spp": 16}), "estimator.mitsuba_spp", "only used with 'engine: mitsuba'"),
    (lambda d: d.update(estimator={"engine": "mitsuba", "mitsuba_spp": 0}), "estimator.mitsuba_spp", "integer >= 1"),
    (lambda d: d.update(estimator={"engine": "mitsuba", "mitsuba_shadows": "yes"}), "estimator.mitsuba_shadows",
     "expected true or false"),
    (lambda d: d["scene"]["emitters"][0].update(radiance=-1), "scene.emitters[0].radiance", "non-negative"),
    (lambda d: d.update(optimize={"object": "ball", "remesh": {"at": [10], "vertices": [900]}, "lambda": [40, 20, 10]}),
     "optimize.lambda", "a list of 2 (one per remesh stage"),
    (lambda d: d.update(optimize={"object": "ball", "downsample": 5}), "optimize.downsample",
     "5 does not divide the film's 24×16 pixels"),
    (lambda d: d.update(optimize={"object": "ball", "remesh": {"at": [10], "vertices": [900]}, "downsample": [2, 0]}),
     "optimize.downsample[1]", "integer >= 1"),
    (lambda d: d.update(optimize={"object": "ball", "remesh": {"at": [10], "vertices": [900]}, "downsample": [3, 1]}),
     "optimize.downsample[0]", "3 does not divide"),
])
def test_invalid_values_name_the_key(tmp_path, mutate, key, words):
    d = experiment()
    mutate(d)
    with pytest.raises(ConfigError) as info:
        parse(d, tmp_path)
    msg = str(info.value)
    assert msg.startswith(f"{tmp_path / 'exp.yaml'}: {key}"), msg
    assert words in msg and "\n" not in msg


def test_engine_defaults_to_psdr_and_mitsuba_keys_parse(tmp_path):
    assert parse(experiment(), tmp_path).estimator.engine == "psdr"
    d = experiment()
    d["estimator"] = {"engine": "mitsuba", "mitsuba_integrator": "prb_projective", "mitsuba_spp": 8,
                      "mitsuba_shadows": True}
    est = parse(d, tmp_path).estimator
    assert (est.engine, est.mitsuba_integrator, est.mitsuba_spp, est.mitsuba_shadows) == \
        ("mitsuba", "prb_projective", 8, True)
    d = experiment()
    d["optimize"] = {"object": "ball", "variants": [{"label": "psdr"}, {"label": "mi", "engine": "mitsuba"}]}
    assert [v.engine for v in parse(d, tmp_path).optimize.variants] == [None, "mitsuba"]
    d["optimize"]["variants"][1]["engine"] = "redner"
    with pytest.raises(ConfigError, match=r"optimize\.variants\[1\]\.engine: unknown 'redner'"):
        parse(d, tmp_path)


def test_yaml_error_reports_line(tmp_path):
    path = tmp_path / "broken.yaml"
    path.write_text("scene:\n  film: {width: 3\n")
    with pytest.raises(ConfigError, match=r"broken.yaml: line \d+, column \d+: invalid YAML"):
        load_experiment(path)


def test_every_shipped_experiment_file_is_valid():
    """All experiment files in configs/ (demo, validation, benchmarks, both paper scales) parse,
    and each paper reproduction exists at both scales."""
    from pathlib import Path
    from psdr_cli.experiment.load import load_experiment
    root = Path(__file__).resolve().parent.parent / "configs"
    files = sorted(root.rglob("*.yaml"))
    assert len(files) > 10
    for f in files:
        load_experiment(f)
    cpu = {f.name for f in (root / "paper" / "cpu").glob("*.yaml")}
    paper = {f.name for f in (root / "paper" / "paper").glob("*.yaml")}
    assert cpu == paper and {"fig9_bunny.yaml", "fig10_glass.yaml", "fig10_shadow.yaml"} <= cpu


def test_stage_schedules_parse_as_one_value_or_one_per_remesh_stage(tmp_path):
    """lambda and downsample: a single value holds for every stage; a list gives one per stage."""
    from psdr_cli.optimisation.stages import stage_at, stage_value
    from psdr_cli.run_folder.fingerprint_v1 import optimize_identity_v1 as optimize_identity
    one = parse(experiment(optimize={"object": "ball"}), tmp_path).optimize
    assert one.lambda_ == (20.0,) and one.downsample == (1,)
    identity = optimize_identity(one)  # written as before schedules existed: old runs keep their fingerprint
    assert identity["lambda_"] == 20.0 and "downsample" not in identity
    opt = parse(experiment(optimize={"object": "ball", "remesh": {"at": [10, 20], "vertices": [900, 1200]},
                                     "lambda": [40, 20, 10], "downsample": [4, 2, 1]}), tmp_path).optimize
    assert opt.lambda_ == (40.0, 20.0, 10.0) and opt.downsample == (4, 2, 1)
    assert [stage_at(opt, i) for i in (0, 9, 10, 19, 20, 99)] == [0, 0, 1, 1, 2, 2]
    assert [stage_value(opt.lambda_, s) for s in (0, 1, 2)] == [40.0, 20.0, 10.0]
    assert stage_value(one.lambda_, 2) == 20.0
    assert optimize_identity(opt)["downsample"] == (4, 2, 1)
