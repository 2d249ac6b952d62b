"""Bad input on the scene paths (XML scenes, OBJ parts and materials, textures, ``psdr evaluate``,
``psdr grad`` options): each gives one ``error:`` line naming the file (or option), key and the
expected form, exit status 2 and no output; and the names, UVs and ids a user writes are read
as written (user names never meet psdr's own Mitsuba ids).

The commands run in-process (``psdr_cli.cli.run``) to keep this module fast."""
import numpy as np
import pytest
import yaml

import mitsuba as mi

from conftest import experiment, write_raw_exr
from psdr_cli import api, cli
from psdr_cli.config.experiment_file import parse
from psdr_cli.errors import ConfigError
from psdr_cli.experiment.load import load_experiment
from psdr_cli.rendering.render import render_view
from psdr_cli.scene import meshes, mitsuba_xml
from psdr_cli.scene.build import build_scene
from psdr_cli.support import backend
from test_mitsuba_scene import write_twins


def psdr(capsys, *args):
    """(exit code, stdout, non-empty stderr lines) of ``psdr ARGS`` run in this process."""
    capsys.readouterr()
    code = cli.run([str(a) for a in args])
    captured = capsys.readouterr()
    return code, captured.out, [ln for ln in captured.err.splitlines() if ln.strip()]


def ply_ascii(path, V, F):
    lines = ["ply", "format ascii 1.0", f"element vertex {len(V)}", "property float x", "property float y",
             "property float z", f"element face {len(F)}", "property list uchar int vertex_indices", "end_header"]
    lines += [" ".join(repr(float(c)) for c in v) for v in V] + [f"3 {a} {b} {c}" for a, b, c in F]
    path.write_text("\n".join(lines) + "\n")


def nan_exr(path):
    texels = np.full((8, 16, 3), 0.5, np.float32)
    texels[0, 0, 0] = np.nan
    write_raw_exr(path, texels)


def write_yaml(tmp, data, name="exp.yaml"):
    (tmp / name).write_text(yaml.safe_dump(data, sort_keys=False))
    return tmp / name


def xml_experiment(tmp, extra="", edit=None):
    """The XML twin scene of test_mitsuba_scene (ball, box, floor, area light), changed by
    ``edit(text)`` and with ``extra`` inside <scene>; returns its experiment file."""
    cfg, _ = write_twins(tmp, extra)
    if edit:
        (tmp / "scene.xml").write_text(edit((tmp / "scene.xml").read_text()))
    return cfg


def box_id(new):
    return lambda text: text.replace('id="box"', f'id="{new}"')


def box_mesh(file):
    return lambda text: text.replace('"box.ply"', f'"{file}"')


BOX_BSDF = '<bsdf type="diffuse"><rgb name="reflectance" value="0.3, 0.6, 0.4"/></bsdf>'
BALL_BSDF = '<bsdf type="diffuse"><rgb name="reflectance" value="0.7, 0.5, 0.3"/></bsdf>'
MEDIUM = '<medium type="homogeneous" id="fog"/>'
CUBE_V, CUBE_F = meshes.cube((0.5, 0.5, 0.5))


def obj_text(vt=False, mtllib="m.mtl", materials=("red",)):
    """A cube as OBJ, its faces split between ``materials`` (with ``vt`` lines when asked)."""
    lines = [f"mtllib {mtllib}"] + [f"v {a} {b} {c + 0.5}" for a, b, c in CUBE_V]
    if vt:
        lines += [f"vt {(i % 4) / 4} {(i // 4) / 2}" for i in range(len(CUBE_V))]
    lines.append("o box")
    for k, face in enumerate(CUBE_F):
        if k % (len(CUBE_F) // len(materials)) == 0 and k // (len(CUBE_F) // len(materials)) < len(materials):
            lines.append(f"usemtl {materials[k // (len(CUBE_F) // len(materials))]}")
        lines.append("f " + " ".join(f"{i + 1}/{i + 1}" if vt else str(i + 1) for i in face))
    return "\n".join(lines) + "\n"


# --------------------------------------------------------------------------------------------
# Bad inputs: (case, files and args) -> one line
# --------------------------------------------------------------------------------------------
def case_xml_id_type(tmp):
    return xml_experiment(tmp, edit=box_id("type")), [], "scene.xml: shape 'type': id 'type' is reserved"


def case_xml_id_internal(tmp):
    return xml_experiment(tmp, edit=box_id("@emitter_00")), [], "shape '@emitter_00': id '@emitter_00' is reserved"


def case_xml_id_dot(tmp):
    return xml_experiment(tmp, edit=box_id("a.b")), [], "shape 'a.b': id 'a.b' contains '.'"


def case_xml_id_not_utf8(tmp):
    """Bytes that are not UTF-8 in an id: Mitsuba loads the file, Python cannot decode the id."""
    cfg = xml_experiment(tmp)
    xml = tmp / "scene.xml"
    data = xml.read_bytes()
    line = data[:data.index(b'id="box"')].count(b"\n") + 1
    xml.write_bytes(data.replace(b'id="box"', b'id="bo\xff\xfex"'))
    return cfg, [], f"scene.xml: line {line}, column 27: not valid UTF-8 (byte 0xff)"


def case_xml_id_not_utf8_declared(tmp):
    """The same bytes under a declared encoding Mitsuba's parser passes through unconverted."""
    cfg = xml_experiment(tmp)
    xml = tmp / "scene.xml"
    data = xml.read_bytes().replace(b'id="box"', b'id="bo\xff\xfex"')
    xml.write_bytes(b'<?xml version="1.0" encoding="windows-1252"?>\n' + data)
    return cfg, [], "scene.xml: an id or name in it is not valid UTF-8"


def case_yaml_name_internal(tmp):
    d = experiment()
    d["scene"]["objects"][0]["name"] = "@sensor_000"
    return write_yaml(tmp, d), [], "scene.objects[0].name: '@sensor_000' is reserved"


def case_sensor_medium(tmp):
    return xml_experiment(tmp, MEDIUM, lambda t: t.replace('<sensor type="perspective">',
                                                           '<sensor type="perspective"><ref id="fog"/>')), [], \
        "scene.xml: sensor 0: participating media are not supported"


def case_obj_mtllib_without_vt_and_bitmap(tmp):
    (tmp / "m.mtl").write_text("newmtl red\nKd 0.5 0.5 0.5\nnewmtl blue\nKd 0.1 0.2 0.9\n")
    (tmp / "box.obj").write_text(obj_text(materials=("red", "blue")))
    mi.Bitmap(np.full((4, 4, 3), 128, np.uint8)).write(str(tmp / "tex.png"))
    d = experiment()
    d["scene"]["objects"][0].update(mesh={"file": "box.obj"}, bsdf={"type": "diffuse", "reflectance": {
        "type": "bitmap", "file": "tex.png"}})
    return write_yaml(tmp, d), [], "scene.objects[0].bsdf: a bitmap texture needs a mesh with UV coordinates"


def case_xml_mesh_far(tmp):
    V = CUBE_V.copy()
    V[0] = [1e30, 0, 0]
    ply_ascii(tmp / "far.ply", V, CUBE_F)
    return xml_experiment(tmp, edit=box_mesh("far.ply")), [], \
        "scene.xml: shape 'box': mesh has 1 vertices with world coordinates beyond ±1e+06"


def case_xml_mesh_all_degenerate(tmp):
    ply_ascii(tmp / "flat.ply", [[0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0]], [[0, 1, 2], [1, 2, 3]])
    return xml_experiment(tmp, edit=box_mesh("flat.ply")), [], \
        "scene.xml: shape 'box': mesh has only degenerate (zero-area) triangles"


def case_mtl_kd_nan(tmp):
    (tmp / "m.mtl").write_text("newmtl red\nKd nan 0 0\n")
    (tmp / "box.obj").write_text(obj_text())
    d = experiment()
    d["scene"]["objects"][0].update(mesh={"file": "box.obj", "split": True})
    del d["scene"]["objects"][0]["bsdf"]
    return write_yaml(tmp, d), [], "m.mtl: material 'red': Kd: expected 3 numbers in [0, 1]"


def case_xml_envmap_nan(tmp):
    nan_exr(tmp / "nan.exr")
    return xml_experiment(tmp, '<emitter type="envmap"><string name="filename" value="nan.exr"/></emitter>'), [], \
        "scene.xml: emitter EnvironmentMapEmitter: 'data' has NaN or infinite values"


def case_xml_texture_nan(tmp):
    nan_exr(tmp / "nan.exr")
    texture = ('<bsdf type="diffuse"><texture type="bitmap" name="reflectance"><string name="filename" '
               'value="nan.exr"/></texture></bsdf>')
    return xml_experiment(tmp, edit=lambda t: t.replace(BOX_BSDF, texture)), [], \
        "scene.xml: shape 'box': BSDF parameter 'reflectance.data' has NaN or infinite values"


def case_yaml_envmap_nan(tmp):
    nan_exr(tmp / "nan.exr")
    d = experiment()
    d["scene"]["emitters"].append({"type": "envmap", "file": "nan.exr"})
    return write_yaml(tmp, d), [], "scene.emitters[1].file: environment map nan.exr has 1 NaN or infinite values"


def case_init_transform_without_mesh(tmp):
    d = experiment(optimize={"object": "ball", "init": {"mesh": None, "transform": {"translate": [0, 0, 1]}}})
    return write_yaml(tmp, d), [], "optimize.init.transform: needs init.mesh"


GRAD = {"parameter": {"object": "ball", "kind": "translate"}}


def case_interior_spp_zero(tmp):
    return write_yaml(tmp, experiment(**GRAD)), ["grad", "--interior-spp", "0"], "--interior-spp: expected a positive"


def case_views_empty_range(tmp):
    return write_yaml(tmp, experiment()), ["render", "--views", "1-0"], "--views: '1-0' is an empty range"


def case_fd_huge(tmp):
    return write_yaml(tmp, experiment(**GRAD)), ["grad", "--fd", "1e30"], \
        "--fd: step 1e+30 is not small against the scene for a translate"


def case_fd_tiny(tmp):
    return write_yaml(tmp, experiment(**GRAD)), ["grad", "--fd", "1e-30"], "--fd: step 1e-30 is not small"


def case_fd_rotation_huge(tmp):
    d = experiment(parameter={"object": "ball", "kind": "rotate"})
    return write_yaml(tmp, d), ["grad", "--fd", "3"], "expected 1e-06 to 0.1: 1e-06 to 0.1 × 1 radian"


CASES = [v for k, v in sorted(globals().items()) if k.startswith("case_")]


@pytest.mark.parametrize("case", CASES, ids=[c.__name__[5:] for c in CASES])
def test_bad_scene_input_is_one_line(tmp_path, capsys, monkeypatch, case):
    monkeypatch.chdir(tmp_path)
    cfg, args, expected = case(tmp_path)
    command, *rest = args or ["render"]
    code, out, err = psdr(capsys, command, cfg, *rest)
    assert code == 2, (code, err)
    assert len(err) == 1, err
    assert err[0].startswith("error: ") and expected in err[0], err[0]
    assert "Traceback" not in out + "\n".join(err)
    assert not (tmp_path / "out").exists(), "a failed command must not leave output behind"


# --------------------------------------------------------------------------------------------
# psdr evaluate: meshes no distance can be measured on
# --------------------------------------------------------------------------------------------
def sphere_ply(path, edit=None):
    V, F = meshes.sphere(1.0, 1)
    V, F = V.tolist(), F.tolist()
    if edit:
        edit(V, F)
    ply_ascii(path, V, F)
    return path


EVALUATE_CASES = [
    ("face_index_out_of_range", "mesh", lambda V, F: F.append([0, 1, len(V) + 5]), "mesh has face indices outside 0.."),
    ("reference_vertex_at_1e30", "reference", lambda V, F: V[0].__setitem__(0, 1e30),
     "mesh has 1 vertices with coordinates beyond ±1e+06"),
    ("mesh_vertex_at_1e30", "mesh", lambda V, F: V[0].__setitem__(0, 1e30), "beyond ±1e+06"),
    ("nan_vertex", "mesh", lambda V, F: V[0].__setitem__(1, float("nan")), "mesh has 1 vertices with NaN"),
    ("zero_area", "reference", lambda V, F: [v.__setitem__(slice(None), [0.0, 0.0, 0.0]) for v in V],
     "mesh has zero surface area"),
]


@pytest.mark.parametrize("which,edit,expected", [c[1:] for c in EVALUATE_CASES], ids=[c[0] for c in EVALUATE_CASES])
def test_evaluate_refuses_meshes_it_cannot_measure(tmp_path, capsys, monkeypatch, which, edit, expected):
    monkeypatch.chdir(tmp_path)
    good = sphere_ply(tmp_path / "good.ply")
    bad = sphere_ply(tmp_path / "bad.ply", edit)
    mesh, reference = (bad, good) if which == "mesh" else (good, bad)
    code, out, err = psdr(capsys, "evaluate", mesh, "--reference", reference, "--samples", "1000",
                          "--json", tmp_path / "e.json")
    assert code == 2 and len(err) == 1, (code, err)
    assert err[0].startswith(f"error: {bad}: ") and expected in err[0], err[0]
    assert not (tmp_path / "e.json").exists()


# --------------------------------------------------------------------------------------------
# Names, ids and UVs as written
# --------------------------------------------------------------------------------------------
ENVIRONMENT = '<emitter type="constant"><rgb name="radiance" value="1"/></emitter>'


@pytest.mark.parametrize("name", ["emitter_00", "sensor_000", "integrator"])
def test_xml_ids_never_replace_psdrs_own_entries(tmp_path, name):
    """An XML shape called like one of psdr's cameras, emitters or its integrator is one more
    object: the environment, the camera and the integrator stay."""
    exp = load_experiment(xml_experiment(tmp_path, ENVIRONMENT, box_id(name)), warn=lambda m: None)
    api.setup(exp)
    scene = build_scene(exp)
    assert {o.name for o in exp.scene.objects} == {"ball", name, "floor"}
    assert name in {s.id() for s in scene.mi_scene.shapes()}
    assert scene.mi_scene.environment() is not None and len(scene.mi_scene.sensors()) == 1
    assert scene.mi_scene.integrator().class_name() == "PathIntegrator"


def test_obj_part_called_like_an_emitter_keeps_the_light(tmp_path):
    """``emitter`` split into its part ``00`` is the object ``emitter_00``, beside the area light."""
    (tmp_path / "m.mtl").write_text("newmtl red\nKd 0.8 0.1 0.1\n")
    (tmp_path / "box.obj").write_text(obj_text().replace("o box", "o 00"))
    d = experiment()
    d["scene"]["objects"][0] = {"name": "emitter", "mesh": {"file": "box.obj", "split": True}}
    exp = load_experiment(write_yaml(tmp_path, d))
    api.setup(exp)
    scene = build_scene(exp)
    assert [o.name for o in exp.scene.objects] == ["emitter_00", "floor"]
    assert [e.class_name() for e in scene.mi_scene.emitters()] == ["AreaLight"]
    assert np.asarray(render_view(scene, 0, 4, seed=1)).mean() > 0.02   # lit, not black


def test_xml_anonymous_shape_numbered_past_the_ids_the_xml_gives(tmp_path):
    anonymous = '<shape type="rectangle"><transform name="to_world"><translate value="0,0,-1"/></transform></shape>'
    exp = load_experiment(xml_experiment(tmp_path, anonymous, box_id("rectangle_0")), warn=lambda m: None)
    assert {o.name for o in exp.scene.objects} == {"ball", "rectangle_0", "floor", "rectangle_1"}


def test_xml_shapes_sharing_a_bsdf_keep_their_ids(tmp_path):
    """Mitsuba's loader would merge shapes sharing a <ref> BSDF into one anonymous mesh."""
    shared = lambda t: (t.replace('<scene version="3.0.0">', '<scene version="3.0.0"><bsdf type="diffuse" id="mat"/>')
                        .replace(BALL_BSDF, '<ref id="mat"/>').replace(BOX_BSDF, '<ref id="mat"/>'))
    exp = load_experiment(xml_experiment(tmp_path, edit=shared), warn=lambda m: None)
    assert {o.name for o in exp.scene.objects} == {"ball", "box", "floor"}
    assert exp.parameter.object == "ball"


def test_xml_instances_render_with_a_warning(tmp_path):
    group = ('<shape type="shapegroup" id="grp"><shape type="cube"><bsdf type="diffuse"/></shape></shape>'
             '<shape type="instance"><ref id="grp"/><transform name="to_world"><scale value="0.2"/>'
             '<translate value="-1,0,0.3"/></transform></shape>')
    cfg = xml_experiment(tmp_path, group)
    warnings = []
    if backend.select_variant().startswith("cuda"):   # refused there (Mitsuba crashed): the test below
        with pytest.raises(ConfigError, match="shapegroup 'grp'"):
            load_experiment(cfg, warn=warnings.append)
        return
    exp = load_experiment(cfg, warn=warnings.append)
    assert len(warnings) == 1 and "shape 'instance_0' is an analytic 'instance'" in warnings[0], warnings
    api.setup(exp)
    scene = build_scene(exp)
    with_group = np.asarray(render_view(scene, 0, 4, seed=1))
    (tmp_path / "plain").mkdir()
    plain = np.asarray(render_view(build_scene(load_experiment(xml_experiment(tmp_path / "plain"))), 0, 4, seed=1))
    assert np.isfinite(with_group).all() and np.abs(with_group - plain).max() > 0.05   # the instance is drawn


def test_xml_instances_are_refused_on_cuda_variants_in_one_line(tmp_path):
    """Mitsuba's cuda_ad_rgb crashed (segmentation fault) rebuilding the scene of
    test_xml_instances_render_with_a_warning on the GPU machine: CUDA variants refuse shapegroups
    at load, naming the file and the group; LLVM variants keep them."""
    xml = tmp_path / "scene.xml"
    with pytest.raises(ConfigError) as err:
        mitsuba_xml.refuse_instances_on_cuda("grp", "cuda_ad_rgb", xml)
    assert "scene.xml" in str(err.value) and "shapegroup 'grp'" in str(err.value)
    assert "llvm_ad_rgb" in str(err.value) and len(str(err.value).splitlines()) == 1
    mitsuba_xml.refuse_instances_on_cuda("grp", "llvm_ad_rgb", xml)


def test_xml_loading_asks_the_variant_check_about_each_shapegroup(tmp_path, monkeypatch):
    group = ('<shape type="shapegroup" id="grp"><shape type="cube"><bsdf type="diffuse"/></shape></shape>'
             '<shape type="instance"><ref id="grp"/></shape>')
    asked = []
    monkeypatch.setattr(mitsuba_xml, "refuse_instances_on_cuda", lambda name, variant, xml: asked.append(name))
    load_experiment(xml_experiment(tmp_path, group), warn=lambda m: None)
    assert asked == ["grp"]


def test_obj_uvs_are_read_as_written(tmp_path):
    """No invented UVs for an OBJ with a material library but no ``vt``, and no atlas for one
    with ``vt`` and two materials: each vertex keeps the UV the file gives it."""
    (tmp_path / "m.mtl").write_text("newmtl red\nKd 0.8 0.1 0.1\nnewmtl blue\nKd 0.1 0.2 0.9\n")
    (tmp_path / "plain.obj").write_text(obj_text(materials=("red", "blue")))
    (tmp_path / "uv.obj").write_text(obj_text(vt=True, materials=("red", "blue")))
    assert meshes.read_mesh_file_uv(tmp_path / "plain.obj")[2] is None
    V, F, uv = meshes.read_mesh_file_uv(tmp_path / "uv.obj")
    for v, t in zip(V, uv):
        i = int(np.flatnonzero(np.all(np.isclose(CUBE_V + [0, 0, 0.5], v), axis=1))[0])
        assert np.allclose(t, [(i % 4) / 4, 1 - (i // 4) / 2]), (i, t)


def test_null_means_absent(tmp_path):
    """``init: {mesh: null}`` is the default initial shape; ``edges: null`` the default edges."""
    d = experiment(optimize={"object": "ball", "init": {"mesh": None}})
    assert parse(d, tmp_path / "x.yaml").optimize.init is None
    cfg, _ = write_twins(tmp_path, scene_keys={"objects": {"floor": {"edges": None}}})
    exp = load_experiment(cfg, warn=lambda m: None)
    assert {o.name: o.edges for o in exp.scene.objects}["floor"] is True
