"""Mitsuba 3 XML scenes (``scene: {mitsuba: ...}``) and OBJ parts (``part`` / ``split``).

The XML scene and its YAML twin (area light, two PLY meshes, a rectangle floor) are written by
the tests; they must render alike and give the same ``psdr grad --fd`` verdict through the CLI.
"""
import json

import mitsuba as mi
import numpy as np
import pytest
import yaml

from psdr_cli import api
from psdr_cli.errors import ConfigError
from psdr_cli.experiment.load import parse_experiment
from psdr_cli.rendering.render import render_view
from psdr_cli.scene import meshes
from psdr_cli.scene.build import build_scene

from conftest import run_cli
from test_gradients import assert_agrees

XML = """<scene version="3.0.0">
  <default name="res" value="16"/>
  <integrator type="path"><integer name="max_depth" value="2"/></integrator>
  <sensor type="perspective">
    <float name="fov" value="40"/><string name="fov_axis" value="x"/>
    <transform name="to_world"><lookat origin="0,-3,2" target="0,0,0.3" up="0,0,1"/></transform>
    <film type="hdrfilm"><integer name="width" value="24"/><integer name="height" value="$res"/></film>
  </sensor>
  <shape type="rectangle" id="light">
    <transform name="to_world"><matrix value="-0.5 0 0 0  0 0.5 0 0  0 0 -1 2.5  0 0 0 1"/></transform>
    <emitter type="area"><rgb name="radiance" value="10"/></emitter>
    <bsdf type="diffuse"><rgb name="reflectance" value="0"/></bsdf>
  </shape>
  <shape type="ply" id="ball"><string name="filename" value="ball.ply"/><boolean name="face_normals" value="true"/>
    <bsdf type="diffuse"><rgb name="reflectance" value="0.7, 0.5, 0.3"/></bsdf></shape>
  <shape type="ply" id="box"><string name="filename" value="box.ply"/><boolean name="face_normals" value="true"/>
    <bsdf type="diffuse"><rgb name="reflectance" value="0.3, 0.6, 0.4"/></bsdf></shape>
  <shape type="rectangle" id="floor"><transform name="to_world"><scale value="2"/></transform>
    <bsdf type="diffuse"><rgb name="reflectance" value="0.5"/></bsdf></shape>
  EXTRA
</scene>
"""
COMMON = {"seed": 1, "output": "out", "parameter": {"kind": "translate", "object": "ball", "axis": [1, 0, 0]},
          "estimator": {"spp": 16, "primary_spp": 64, "boundary_spp": 64}}
TWIN = {"film": {"width": 24, "height": 16}, "max_depth": 2,
        "cameras": [{"origin": [0, -3, 2], "target": [0, 0, 0.3], "fov": 40}],
        "emitters": [{"type": "area", "center": [0, 0, 2.5], "normal": [0, 0, -1], "size": [1, 1], "radiance": 10}],
        "objects": [{"name": "ball", "mesh": {"file": "ball.ply"}, "bsdf": {"type": "diffuse", "reflectance": [0.7, 0.5, 0.3]}},
                    {"name": "box", "mesh": {"file": "box.ply"}, "bsdf": {"type": "diffuse", "reflectance": [0.3, 0.6, 0.4]}},
                    {"name": "floor", "mesh": {"shape": "plane", "size": 4}, "edges": False}]}


def write_twins(folder, extra_xml="", scene_keys=None):
    """scene.xml, its meshes, and the experiments xml.yaml (the XML scene) and yaml.yaml (its twin)."""
    V, F = meshes.sphere(0.4, 2)
    meshes.write_ply(folder / "ball.ply", V + [0, 0, 0.5], F)
    V, F = meshes.cube((0.5, 0.5, 0.5))
    meshes.write_ply(folder / "box.ply", V + [0.9, 0.5, 0.25], F)
    (folder / "scene.xml").write_text(XML.replace("EXTRA", extra_xml))
    scene = {"mitsuba": "scene.xml", "params": {"res": 16}, "objects": {"floor": {"edges": False}}, **(scene_keys or {})}
    (folder / "xml.yaml").write_text(yaml.safe_dump({"name": "xml", **COMMON, "scene": scene}, sort_keys=False))
    (folder / "yaml.yaml").write_text(yaml.safe_dump({"name": "yaml", **COMMON, "scene": TWIN}, sort_keys=False))
    return folder / "xml.yaml", folder / "yaml.yaml"


def test_xml_scene_is_read_like_its_yaml_twin(tmp_path):
    xml_cfg, yaml_cfg = write_twins(tmp_path)
    ex, ey = api.load_experiment(xml_cfg), api.load_experiment(yaml_cfg)
    assert (ex.scene.width, ex.scene.height, ex.scene.max_depth) == (24, 16, 2)   # $res substituted
    assert {o.name: (o.edges, o.bsdf.type) for o in ex.scene.objects} == {
        "ball": (True, "diffuse"), "box": (True, "diffuse"), "floor": (False, "diffuse")}
    assert [e.type for e in ex.scene.emitters] == ["area"]
    assert not any(o.smooth for o in ex.scene.objects)   # the rectangle's normals are its face normal: flat
    cx, cy = ex.scene.cameras[0], ey.scene.cameras[0]
    direction = np.subtract(cy.target, cy.origin)
    assert np.allclose(cx.origin, cy.origin, atol=1e-5) and np.allclose(cx.up, [0, 0.4930, 0.8700], atol=1e-3)
    assert np.allclose(np.subtract(cx.target, cx.origin), direction / np.linalg.norm(direction), atol=1e-5)
    api.setup(ex)
    sx, sy = build_scene(ex), build_scene(ey)
    for name in ("ball", "box"):
        assert np.array_equal(sx.objects[name].vertices, sy.objects[name].vertices)
        assert np.array_equal(sx.objects[name].faces, sy.objects[name].faces)
    assert np.allclose(np.sort(sx.objects["floor"].vertices, 0), np.sort(sy.objects["floor"].vertices, 0))
    ix, iy = render_view(sx, 0, 256, seed=3), render_view(sy, 0, 256, seed=3)
    # Same scene, same seeds; the floor's two triangles are split along the other diagonal
    # (Mitsuba's rectangle), which changes its shading frames and so individual samples only.
    assert ix.mean() == pytest.approx(iy.mean(), rel=0.01)
    assert np.abs(ix - iy).mean() < 0.01 * iy.mean() * 3 and np.abs(ix - iy).max() < 0.05


def test_xml_grad_agrees_with_finite_differences_like_its_yaml_twin(tmp_path, run_psdr):
    """``psdr grad --fd`` through the CLI (in this process) on both: the same verdict and compatible
    estimates."""
    xml_cfg, yaml_cfg = write_twins(tmp_path)
    views = {}
    for name, cfg in (("xml", xml_cfg), ("yaml", yaml_cfg)):
        proc = run_psdr("grad", cfg, "--fd", 0.003, "--spp", 128, "--fd-spp", 16384, "--out", tmp_path / "out")
        assert proc.returncode == 0, proc.stderr
        assert "agrees" in proc.stdout and "DISAGREES" not in proc.stdout
        views[name] = json.loads((tmp_path / "out" / name / "grad" / "summary.json").read_text())["views"][0]
        assert_agrees(views[name])
    sx, sy = views["xml"]["fd_agreement"]["sum"], views["yaml"]["fd_agreement"]["sum"]
    assert abs(sx["estimate"] - sy["estimate"]) < 3 * np.hypot(sx["estimate_se"], sy["estimate_se"])
    assert abs(sx["fd"] - sy["fd"]) < 3 * np.hypot(sx["fd_se"], sy["fd_se"])
    assert views["xml"]["sums"]["interior"] == pytest.approx(views["yaml"]["sums"]["interior"], rel=0.05, abs=0.05)


def test_analytic_shapes_warn_and_delta_lights_are_refused(tmp_path, run_psdr):
    sphere = '<shape type="sphere" id="orb"><point name="center" value="-0.8,0.4,0.3"/><float name="radius" value="0.3"/></shape>'
    xml_cfg, _ = write_twins(tmp_path, sphere)
    warnings = []
    exp = api.load_experiment(xml_cfg, warn=warnings.append)
    assert len(warnings) == 1 and "shape 'orb' is an analytic 'sphere'" in warnings[0]
    assert "orb" not in [o.name for o in exp.scene.objects]
    write_twins(tmp_path, '<emitter type="point"><point name="position" value="0,0,3"/></emitter>')
    proc = run_psdr("render", xml_cfg, cwd=tmp_path)
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1
    assert "scene.xml: emitter PointLight: 'point' lights are not supported" in proc.stderr


def test_bad_xml_is_one_line_naming_file_and_line(tmp_path, run_psdr):
    """Through the real entry point (Mitsuba's XML parser takes part), then a key XML does not use
    (in this process)."""
    xml_cfg, _ = write_twins(tmp_path)
    text = (tmp_path / "scene.xml").read_text().replace("</shape>\n  <shape type=\"rectangle\" id=\"floor\">",
                                                       "</shap>\n  <shape type=\"rectangle\" id=\"floor\">")
    (tmp_path / "scene.xml").write_text(text)
    proc = run_cli("render", xml_cfg, cwd=tmp_path)
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1, proc.stderr
    line = text[:text.index("</shap>")].count("\n") + 1
    assert f"scene.xml: line {line}, column" in proc.stderr and "mismatch" in proc.stderr
    write_twins(tmp_path, scene_keys={"params": {"rez": 16}})
    proc = run_psdr("render", xml_cfg, cwd=tmp_path)
    assert "xml.yaml: scene.params.rez: scene.xml does not use $rez" in proc.stderr


def test_xml_errors_name_the_experiment_keys(tmp_path):
    xml_cfg, _ = write_twins(tmp_path, scene_keys={"objects": {"flor": {"edges": False}}})
    with pytest.raises(ConfigError, match=r"scene\.objects\.flor: no mesh shape 'flor' in scene\.xml"):
        api.load_experiment(xml_cfg)
    d = yaml.safe_load(xml_cfg.read_text())
    d["scene"]["objects"] = {}
    d["parameter"]["object"] = "light"   # an emitter, not an object
    xml_cfg.write_text(yaml.safe_dump(d))
    with pytest.raises(ConfigError, match=r"parameter\.object: unknown object 'light' \(scene objects: "):
        api.load_experiment(xml_cfg)


def test_scene_up_sets_camera_and_rotation_defaults(tmp_path):
    write_twins(tmp_path)
    d = {"scene": {"mitsuba": "scene.xml", "up": [0, 2, 0],
                   "cameras": {"orbit": {"count": 2, "radius": 2, "elevation_deg": 0}}},
         "parameter": {"kind": "rotate", "object": "ball"}}
    exp = parse_experiment(d, tmp_path / "e.yaml", cwd=tmp_path)
    assert exp.parameter.axis == (0.0, 1.0, 0.0)
    assert all(c.up == (0.0, 1.0, 0.0) and abs(c.origin[1]) < 1e-9 for c in exp.scene.cameras)
    assert len(exp.scene.cameras) == 2 and exp.scene.width == 24


OBJ = """mtllib parts.mtl
v 0 0 0
v 1 0 0
v 1 1 0
v 0 1 0
v 0 0 1
v 1 0 1
v 1 1 1
o seat
usemtl red
f 1 2 3 4
g back
usemtl blue
f 5/1 6/1 7/1
f -4 -1 5
"""
MTL = "newmtl red\nKd 0.8 0.1 0.1\nnewmtl blue\nKd 0.1 0.2 0.9\n"


def test_obj_groups_split_into_objects_with_mtl_colours(tmp_path):
    (tmp_path / "chair.obj").write_text(OBJ)
    (tmp_path / "parts.mtl").write_text(MTL)
    d = {"scene": {"cameras": [{"origin": [0, -3, 1], "target": [0.5, 0.5, 0.5]}],
                   "emitters": [{"type": "constant", "radiance": 1}],
                   "objects": [{"name": "chair", "mesh": {"file": "chair.obj", "split": True},
                                "parts": {"back": {"edges": False}}},
                               {"name": "seat", "mesh": {"file": "chair.obj", "part": "seat"},
                                "bsdf": {"type": "diffuse", "reflectance": 0.2},
                                "transform": {"translate": [3, 0, 0]}}]},
         "parameter": {"kind": "translate", "object": "chair_back"}}
    exp = parse_experiment(d, tmp_path / "e.yaml", cwd=tmp_path)
    objs = {o.name: o for o in exp.scene.objects}
    assert list(objs) == ["chair_seat", "chair_back", "seat"]
    assert objs["chair_seat"].bsdf.params["reflectance"] == (0.8, 0.1, 0.1)   # from the MTL
    assert objs["chair_back"].bsdf.params["reflectance"] == (0.1, 0.2, 0.9)
    assert objs["seat"].bsdf.params["reflectance"] == 0.2                     # given: kept
    assert not objs["chair_back"].edges and objs["chair_seat"].edges
    api.setup(exp)
    scene = build_scene(exp)
    seat, back = scene.objects["chair_seat"], scene.objects["chair_back"]
    assert seat.vertices.shape == (4, 3) and seat.faces.shape == (2, 3)        # the quad, fanned
    assert back.vertices.shape == (4, 3) and back.faces.shape == (2, 3)
    assert np.allclose(scene.objects["seat"].vertices, seat.vertices + [3, 0, 0])
    keys = set(mi.traverse(scene.mi_scene).keys())
    assert {"chair_seat.vertex_positions", "chair_back.vertex_positions", "seat.vertex_positions"} <= keys
    d["scene"]["objects"][1]["mesh"]["part"] = "legs"
    with pytest.raises(ConfigError, match=r"scene\.objects\[1\]\.mesh\.file: no part 'legs' in chair\.obj "
                                          r"\(parts: seat, back\)"):
        build_scene(parse_experiment(d, tmp_path / "e.yaml", cwd=tmp_path))
