"""Bad input through the CLI: one clear line naming file and key, non-zero exit, no traceback,
and nothing written to the output folder. Most cases run ``psdr`` in this process (run_psdr,
~4 s of imports fewer each); the cases in REAL_PROCESS go through the real entry point
(``python -m psdr_cli``)."""
import numpy as np
import pytest

from conftest import experiment, run_cli


def ply_ascii(path, V, F):
    lines = ["ply", "format ascii 1.0", f"element vertex {len(V)}", "property float x", "property float y",
             "property float z", f"element face {len(F)}", "property list uchar int vertex_indices", "end_header"]
    lines += [" ".join(str(c) for c in v) for v in V] + [f"3 {a} {b} {c}" for a, b, c in F]
    path.write_text("\n".join(lines) + "\n")


TETRA_V = [[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]
TETRA_F = [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]]


def with_mesh_file(name):
    d = experiment()
    d["scene"]["objects"][0]["mesh"] = {"file": name}
    return d


def case_yaml_syntax(tmp):
    return "scene:\n  film: {width: 3\n  max_depth: 2\n", [], "invalid YAML"


def case_unknown_key(tmp):
    d = experiment()
    d["scene"]["objects"][0]["trasform"] = {"translate": [0, 0, 1]}
    return d, [], "scene.objects[0].trasform: unknown key"


def case_wrong_type(tmp):
    d = experiment()
    d["scene"]["film"]["width"] = "wide"
    return d, [], "scene.film.width: expected an integer"


def case_missing_mesh_file(tmp):
    return with_mesh_file("nowhere.ply"), [], "scene.objects[0].mesh.file: mesh file not found"


def case_empty_mesh_file(tmp):
    (tmp / "empty.ply").write_text("")
    return with_mesh_file("empty.ply"), [], "scene.objects[0].mesh.file: "


def case_garbage_mesh_file(tmp):
    (tmp / "garbage.obj").write_bytes(b"\x00\x01 not a mesh \xff\xfe")
    return with_mesh_file("garbage.obj"), [], "scene.objects[0].mesh.file: "


def case_nan_vertices(tmp):
    V = [list(v) for v in TETRA_V]
    V[2][1] = float("nan")
    ply_ascii(tmp / "nan.ply", V, TETRA_F)
    return with_mesh_file("nan.ply"), [], "NaN"


def case_degenerate_faces(tmp):
    V = TETRA_V + [[2, 0, 0]]
    ply_ascii(tmp / "degen.ply", V, TETRA_F + [[0, 1, 4]])  # collinear triangle
    return with_mesh_file("degen.ply"), [], "1 degenerate (zero-area) triangles"


def case_zero_spp(tmp):
    return experiment(estimator={"spp": 0}), [], "estimator.spp: expected an integer >= 1, got 0"


def case_negative_spp_flag(tmp):
    return experiment(), ["--spp", "-4"], "--spp: expected a positive number"


def case_unknown_bsdf(tmp):
    d = experiment()
    d["scene"]["objects"][0]["bsdf"] = {"type": "difuse"}
    return d, [], "scene.objects[0].bsdf.type: unknown 'difuse' (expected diffuse, roughconductor"


def case_unknown_parameter_object(tmp):
    return experiment(parameter={"object": "bunny", "kind": "translate"}), [], \
        "parameter.object: unknown object 'bunny' (scene objects: ball, floor)"


def case_camera_origin_is_target(tmp):
    d = experiment()
    d["scene"]["cameras"] = [{"origin": [1, 2, 3], "target": [1, 2, 3]}]
    return d, [], "scene.cameras[0]: origin and target are the same point"


def case_missing_scene(tmp):
    d = experiment()
    del d["scene"]
    return d, [], ": scene: missing (required)"


def case_missing_envmap(tmp):
    d = experiment()
    d["scene"]["emitters"].append({"type": "envmap", "file": "sky.exr"})
    return d, [], "scene.emitters[1].file: environment map not found"


def case_views_out_of_range(tmp):
    return experiment(), ["--views", "0,5"], "--views: view 5 does not exist"


def case_empty_file(tmp):
    return "", [], "the file is empty"


def case_bsdf_value_rejected_by_mitsuba(tmp):
    d = experiment()
    d["scene"]["objects"][0]["bsdf"] = {"type": "roughconductor", "material": "Unobtainium"}
    return d, [], "scene.objects[0].bsdf: Mitsuba rejected the BSDF"


CASES = [v for k, v in sorted(globals().items()) if k.startswith("case_")]
#: cases run as a real process: the first error a user meets, and one that Mitsuba's own code
#: (its logger included) takes part in
REAL_PROCESS = {"yaml_syntax", "bsdf_value_rejected_by_mitsuba"}


@pytest.mark.parametrize("case", CASES, ids=[c.__name__[5:] for c in CASES])
def test_bad_input_gives_one_line_and_nonzero_exit(tmp_path, write_cfg, run_psdr, case):
    data, extra, expected = case(tmp_path)
    cfg = write_cfg(data)
    run = run_cli if case.__name__[5:] in REAL_PROCESS else run_psdr
    proc = run("render", cfg, *extra, cwd=tmp_path)
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert proc.returncode == 2, (proc.returncode, proc.stderr)
    assert len(lines) == 1, proc.stderr
    assert "Traceback" not in proc.stderr + proc.stdout
    assert lines[0].startswith("error: ")
    assert expected in lines[0], lines[0]
    if not extra:
        assert lines[0].startswith(f"error: {cfg}: "), lines[0]  # experiment errors name the file
    assert not (tmp_path / "out").exists(), "a failed run must not leave output behind"


def test_missing_config_file(tmp_path, run_psdr):
    """In this process: read_file's other errors (yaml_syntax, in REAL_PROCESS) take the same path
    through the real entry point."""
    proc = run_psdr("render", tmp_path / "nope.yaml", cwd=tmp_path)
    assert proc.returncode == 2 and "nope.yaml: file not found" in proc.stderr
    assert "Traceback" not in proc.stderr


def test_repair_drops_degenerate_faces(tmp_path):
    from psdr_cli.config.values import Where
    from psdr_cli.scene.meshes import validate_mesh
    V = np.array(TETRA_V + [[2, 0, 0]], float)
    F = np.array(TETRA_F + [[0, 1, 4]])
    V2, F2 = validate_mesh(V, F, Where("x.yaml", "m"), repair=True)
    assert len(F2) == 4 and len(V2) == 4 and np.allclose(V2, TETRA_V)
