"""Textures that survive remeshing and the export of a run (issue 39, items 3, 4, 6): after a
remesh the new mesh gets an xatlas atlas and the texture is transferred from the old surface by
closest points; ``psdr export`` writes OBJ + MTL + PNG and a binary glTF of a run or a mesh."""
import io
import json
from dataclasses import replace

import mitsuba as mi
import numpy as np
import pytest
import yaml
from PIL import Image

from conftest import bit_reproducible, write_raw_exr
from psdr_cli import cli, load_experiment
from psdr_cli.config.optimize_section import OptimizeConfig
from psdr_cli.geometry import atlas
from psdr_cli.rendering.render import render_view
from psdr_cli.run_folder.log import read_log
from psdr_cli.scene import meshes
from psdr_cli.scene.build import build_scene
from psdr_cli.scene.material_params import texture_experiment
from psdr_cli.support import backend, fileio

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


@pytest.fixture(scope="module")
def full_run(tmp_path_factory):
    """A textured run remeshed at its start (remesh.initial) and at iteration 3, 5 iterations."""
    tmp = tmp_path_factory.mktemp("full")
    path, run = run_data(tmp, 5)
    assert cli.run(["optimize", str(path)]) == 0
    return path, run


@bit_reproducible
def test_textured_run_with_a_remesh_resumes_exactly(tmp_path, full_run):
    """The textured run completes, with UVs split at the atlas's seams in its state; stopped at
    iteration 2 and resumed, it reproduces the uninterrupted run: losses, texture and final mesh."""
    _, run_full = full_run
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


# --------------------------------------------------------------------------------------------
# psdr export
# --------------------------------------------------------------------------------------------
def read_glb(path):
    """(json, {attribute: array}, indices, image bytes) of a binary glTF with one primitive,
    parsed from the bytes (independently of the writer)."""
    data = path.read_bytes()
    assert data[:4] == b"glTF" and int.from_bytes(data[4:8], "little") == 2
    n = int.from_bytes(data[12:16], "little")
    assert data[16:20] == b"JSON"
    doc = json.loads(data[20:20 + n])
    m = int.from_bytes(data[20 + n:24 + n], "little")
    assert data[24 + n:28 + n] == b"BIN\x00"
    blob = data[28 + n:28 + n + m]
    kinds = {5126: np.float32, 5125: np.uint32, 5123: np.uint16, 5121: np.uint8}
    width = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}

    def accessor(i):
        a = doc["accessors"][i]
        view = doc["bufferViews"][a["bufferView"]]
        start = view.get("byteOffset", 0) + a.get("byteOffset", 0)
        dtype = kinds[a["componentType"]]
        count = a["count"] * width[a["type"]]
        return np.frombuffer(blob, dtype, count, start).reshape(a["count"], -1)

    prim = doc["meshes"][0]["primitives"][0]
    attributes = {k: accessor(v) for k, v in prim["attributes"].items()}
    image = None
    if doc.get("images"):
        view = doc["bufferViews"][doc["images"][0]["bufferView"]]
        image = blob[view.get("byteOffset", 0):view.get("byteOffset", 0) + view["byteLength"]]
    return doc, attributes, accessor(prim["indices"]).reshape(-1, 3), image


def test_export_of_a_textured_run_round_trips_and_renders_alike(tmp_path, full_run):
    """``psdr export RUN``: the OBJ (read by trimesh) and the GLB (parsed from its bytes) hold the
    final mesh, its UVs and the recovered texture in a diffuse material; Mitsuba's own ``path``
    integrator rendering the OBJ with its PNG agrees with psdr's render of the run's state."""
    import trimesh
    from psdr_cli.optimisation.problem import Problem
    from psdr_cli.run_folder.state import State
    from psdr_cli.scene.build import emitter_dict, sensor_dict
    path, run = full_run
    out = tmp_path / "asset"
    assert cli.run(["export", str(run), "--out", str(out)]) == 0
    state = State.load(run / "state.npz")
    V, F = meshes.read_mesh_file(run / "final.ply")
    names = sorted(p.name for p in out.iterdir())
    assert names == ["albedo.png", "export.json", "mesh.glb", "mesh.mtl", "mesh.obj"], names
    # OBJ + MTL
    obj = trimesh.load(str(out / "mesh.obj"), force="mesh", process=False)
    assert np.allclose(obj.vertices, V, atol=1e-6) and np.array_equal(obj.faces, F)
    assert np.allclose(obj.visual.uv[:, 0], state.uv[:, 0], atol=1e-6)
    assert np.allclose(1 - obj.visual.uv[:, 1], state.uv[:, 1], atol=1e-6)  # OBJ's v runs up
    assert "map_Kd albedo.png" in (out / "mesh.mtl").read_text()
    png = np.asarray(mi.Bitmap(str(out / "albedo.png")).convert(component_format=mi.Struct.Type.Float32,
                                                                 srgb_gamma=False))
    texture = np.clip(state.values["albedo"], 0, 1)
    assert png.shape == texture.shape and np.abs(png - texture).max() < 0.02  # 8-bit sRGB
    # GLB
    doc, attributes, indices, image = read_glb(out / "mesh.glb")
    assert np.allclose(attributes["POSITION"], V, atol=1e-6) and np.array_equal(indices, F)
    assert np.allclose(attributes["TEXCOORD_0"], state.uv, atol=1e-6)  # glTF's v runs down, as Mitsuba's
    pbr = doc["materials"][0]["pbrMetallicRoughness"]
    assert pbr["metallicFactor"] == 0 and pbr["roughnessFactor"] == 1 and "baseColorTexture" in pbr
    assert np.array_equal(np.asarray(Image.open(io.BytesIO(image)).convert("RGB")),
                          np.asarray(Image.open(out / "albedo.png").convert("RGB")))  # the PNG's texels
    # Mitsuba renders the exported asset as psdr renders the run's state
    exp = load_experiment(path)
    backend.activate(exp)
    problem = Problem.from_state(exp, state, None)
    cfg = exp.scene
    for v in (0, 2):
        ours = render_view(problem.scene, v, 256, seed=3)
        theirs = np.asarray(mi.render(mi.load_dict({
            "type": "scene", "integrator": {"type": "path", "max_depth": cfg.max_depth},
            "sensor": sensor_dict(cfg.cameras[v], cfg.width, cfg.height),
            "light": emitter_dict(cfg.emitters[0], str(exp.file)),
            "asset": {"type": "obj", "filename": str(out / "mesh.obj"), "face_normals": True,
                      "bsdf": {"type": "diffuse", "reflectance": {"type": "bitmap",
                                                                  "filename": str(out / "albedo.png")}}}}),
            spp=256, seed=5), np.float64)
        rel = np.abs(ours - theirs).mean() / theirs.mean()
        print(f"view {v}: mean |psdr - Mitsuba(export)| / mean = {rel:.4f}")
        assert rel < 0.03, rel
    problem.release()


def psdr(capsys, *args):
    capsys.readouterr()
    code = cli.run([str(a) for a in args])
    return code, [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]


def test_export_of_a_mesh_and_bad_inputs(tmp_path, capsys):
    """A mesh file exports grey (baseColorFactor, Kd) or with --texture; a texture on a mesh
    without UVs, a non-finite texel, an unwritable or foreign output folder and a missing source
    are one line each, and leave no output and no temporary folder behind."""
    V, F, uv = meshes.uv_sphere(0.5, 6)
    obj = tmp_path / "ball.obj"
    obj.write_text("\n".join([f"v {x} {y} {z}" for x, y, z in V] + [f"vt {u} {1 - v}" for u, v in uv]
                             + [f"f {a + 1}/{a + 1} {b + 1}/{b + 1} {c + 1}/{c + 1}" for a, b, c in F]) + "\n")
    meshes.write_ply(tmp_path / "plain.ply", *meshes.weld_vertices(V, F))
    fileio.write_rgb_exr(tmp_path / "tex.exr", TEXTURE)
    write_raw_exr(tmp_path / "nan.exr", np.where(TEXTURE > 0.85, np.nan, TEXTURE))
    assert psdr(capsys, "export", tmp_path / "plain.ply")[0] == 0
    doc, attributes, indices, image = read_glb(tmp_path / "plain_export" / "mesh.glb")
    pbr = doc["materials"][0]["pbrMetallicRoughness"]
    assert image is None and np.allclose(pbr["baseColorFactor"], [0.5, 0.5, 0.5, 1], atol=0.003)
    assert "Kd 0.5 0.5 0.5" in (tmp_path / "plain_export" / "mesh.mtl").read_text()
    assert psdr(capsys, "export", obj, "--texture", tmp_path / "tex.exr", "--out", tmp_path / "ok")[0] == 0
    doc, attributes, _, image = read_glb(tmp_path / "ok" / "mesh.glb")
    assert np.allclose(np.sort(attributes["TEXCOORD_0"], 0), np.sort(uv, 0), atol=1e-6) and image is not None
    assert psdr(capsys, "export", obj, "--texture", tmp_path / "tex.exr", "--out", tmp_path / "ok")[0] == 0  # replaces
    (tmp_path / "foreign").mkdir()
    (tmp_path / "foreign" / "notes.txt").write_text("mine")
    (tmp_path / "afile").write_text("")
    cases = [((tmp_path / "plain.ply", "--texture", tmp_path / "tex.exr"), "no UV coordinates"),
             ((obj, "--texture", tmp_path / "nan.exr"), "NaN or infinite"),
             ((obj, "--out", tmp_path / "afile" / "sub"), "cannot write the export folder"),
             ((obj, "--out", tmp_path / "foreign"), "not a psdr export"),
             ((tmp_path / "missing.ply",), "not found"),
             ((tmp_path / "foreign",), "not a `psdr optimize` run folder")]
    for args, expected in cases:
        code, err = psdr(capsys, "export", *args)
        assert code == 2 and len(err) == 1 and expected in err[0], (args, err)
    assert not (tmp_path / "ball_export").exists() and (tmp_path / "foreign" / "notes.txt").read_text() == "mine"
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporary folder left


def test_rotated_environment_lights_as_the_rotated_emitter(tmp_path):
    """The exported environment map, used with the emitter's own frame, gives the radiance the
    rotated emitter gives (Mitsuba's envmap evaluated in random directions)."""
    import drjit as dr
    from psdr_cli.optimisation.unknowns.environment_rotation import rotate_latlong
    from psdr_cli.scene.build import environment_to_world
    backend.select_variant("auto")
    y, x = np.mgrid[0:32, 0:64]
    image = np.stack([1 + np.sin(x / 64 * 2 * np.pi), 1 + np.cos(y / 32 * np.pi), 1 + 0.5 * np.sin(x / 32 * 2 * np.pi)], -1)
    axis, angle, deg = (0.3, 0.2, 1.0), 0.7, 25.0
    M0 = environment_to_world(deg)
    R = meshes.rotation_matrix(axis, np.degrees(angle))
    M = np.array(M0.matrix, np.float64)[:3, :3]
    rotated = rotate_latlong(image, M.T @ R.T @ M)
    Rm = np.eye(4)
    Rm[:3, :3] = R

    def radiance(img, to_world, d):
        em = mi.load_dict({"type": "envmap", "bitmap": mi.Bitmap(np.ascontiguousarray(img, np.float32)),
                           "to_world": to_world})
        si = dr.zeros(mi.SurfaceInteraction3f, len(d))
        si.wi = mi.Vector3f(*(-d.T))
        return np.asarray(em.eval(si), np.float64).reshape(len(d), 3)

    d = np.random.default_rng(1).normal(size=(400, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    want = radiance(image, mi.ScalarTransform4f(Rm) @ M0, d)
    got = radiance(rotated, M0, d)
    err = np.abs(got - want).mean() / np.abs(want).mean()
    print(f"rotated environment: mean relative error {err:.4f}")
    assert err < 0.02, err
