"""Scene building: cameras, emitters, meshes and transforms as Mitsuba sees them."""
import math

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from psdr_cli.api import setup
from psdr_cli.experiment.load import parse_experiment
from psdr_cli.rendering.render import render_view
from psdr_cli.scene import meshes
from psdr_cli.scene.build import build_scene
from psdr_cli.support import fileio as io

from conftest import experiment


@pytest.fixture
def exp_of(tmp_path):
    def make(d):
        exp = parse_experiment(d, tmp_path / "exp.yaml", cwd=tmp_path)
        setup(exp)
        return exp
    return make


def test_cameras_keep_order_position_and_fov(exp_of):
    d = experiment()
    d["scene"]["cameras"] = [{"orbit": {"count": 5, "radius": 3, "elevation_deg": 10, "fov": 30}}]
    exp = exp_of(d)
    scene = build_scene(exp)
    assert len(scene.sensors) == 5
    for cam, sensor in zip(exp.scene.cameras, scene.sensors):
        origin = sensor.world_transform() @ mi.ScalarPoint3f(0, 0, 0)
        assert np.allclose(np.array(origin).ravel(), cam.origin, atol=1e-5)
        assert mi.traverse(sensor)["x_fov"][0] == pytest.approx(30, abs=1e-4)
        assert tuple(sensor.film().size()) == (24, 16)


def test_object_transform_scale_rotate_translate(exp_of):
    d = experiment()
    d["scene"]["objects"][0] = {"name": "box", "mesh": {"shape": "cube", "size": [2, 1, 1]},
                                "transform": {"scale": 0.5, "rotate": {"axis": [0, 0, 1], "angle_deg": 90},
                                              "translate": [1, 2, 3]}}
    scene = build_scene(exp_of(d))
    V = scene.objects["box"].vertices
    assert np.allclose(V.min(0), [0.75, 1.5, 2.75]) and np.allclose(V.max(0), [1.25, 2.5, 3.25])
    shape = [s for s in scene.mi_scene.shapes() if s.id() == "box"][0]
    P = np.array(mi.traverse(shape)["vertex_positions"]).reshape(-1, 3)
    assert np.allclose(P, V, atol=1e-6)


def test_bunny_comes_from_pymeshlab_z_up_and_sized():
    V, F = meshes.bunny(size=2.0, faces=1500)
    assert meshes.bunny_path().exists() and "pymeshlab" in str(meshes.bunny_path())
    ext = V.max(0) - V.min(0)
    assert ext.max() == pytest.approx(2.0) and V[:, 2].min() == pytest.approx(0.0)
    assert 1000 < len(F) <= 1500 and not meshes.degenerate_faces(V, F).any()
    # the ears point up: the top 10 % of the bunny is much narrower than its base
    top = V[V[:, 2] > 0.9 * V[:, 2].max()]
    assert np.ptp(top[:, 0]) * np.ptp(top[:, 1]) < 0.25 * ext[0] * ext[1]


def test_procedural_shapes_are_closed_and_valid():
    for V, F in (meshes.sphere(1, 2), meshes.cube((1, 2, 3)), meshes.torus(1, 0.3, 16, 8)):
        import trimesh
        assert trimesh.Trimesh(V, F, process=False).is_watertight
        assert not meshes.degenerate_faces(V, F).any()


def test_stand_ins_have_ears_and_a_groove():
    """eared_blob: closed, outward, two thin ears reaching ear_length above the sphere;
    grooved_block: closed, outward, the box volume less the half-cylinder groove."""
    import trimesh
    V, F = meshes.eared_blob(radius=0.3, ear_length=0.45, ear_width=0.12, subdivisions=4)
    m = trimesh.Trimesh(V, F, process=False)
    assert m.is_watertight and m.is_winding_consistent and m.volume > 0
    assert V[:, 2].max() > 0.3 + 0.8 * 0.45 * np.cos(np.radians(25))
    tips = V[V[:, 2] > 0.6]
    assert (tips[:, 0] > 0).any() and (tips[:, 0] < 0).any() and np.ptp(tips[:, 1]) < 0.2  # two thin ears
    V, F = meshes.grooved_block((0.9, 0.7, 0.45), groove_radius=0.16, segments=64)
    m = trimesh.Trimesh(V, F, process=False)
    assert m.is_watertight and m.is_winding_consistent and not meshes.degenerate_faces(V, F).any()
    assert m.volume == pytest.approx(0.9 * 0.7 * 0.45 - 0.9 * np.pi * 0.16 ** 2 / 2, rel=1e-3)
    assert V[:, 2].min() == pytest.approx(0.0) and V[:, 2].max() == pytest.approx(0.45)


def floor_brightness(exp_of, normal):
    d = experiment()
    d["scene"]["objects"] = [{"name": "floor", "mesh": {"shape": "plane", "size": 4}}]
    d["scene"]["emitters"][0]["normal"] = normal
    scene = build_scene(exp_of(d))
    return render_view(scene, 0, spp=16, seed=0).mean()


def test_area_light_is_one_sided_and_faces_its_normal(exp_of):
    down, up = floor_brightness(exp_of, [0, 0, -1]), floor_brightness(exp_of, [0, 0, 1])
    assert down > 0.05 and up < 1e-6 * down


def test_area_light_size_and_radiance_give_the_expected_irradiance(exp_of):
    """Floor point under a w×h light at height z: E ≈ L·A/z² for a small light (Lambertian: B = ρE/π)."""
    d = experiment()
    d["scene"]["objects"] = [{"name": "floor", "mesh": {"shape": "plane", "size": 0.2},
                              "bsdf": {"type": "diffuse", "reflectance": 0.5}}]
    d["scene"]["emitters"] = [{"type": "area", "center": [0, 0, 4], "normal": [0, 0, -1], "size": [0.2, 0.1],
                               "radiance": 100}]
    d["scene"]["cameras"] = [{"origin": [0, 0, 1], "target": [0, 0, 0], "up": [0, 1, 0], "fov": 2}]
    img = render_view(build_scene(exp_of(d)), 0, spp=64, seed=0)
    expected = 0.5 / math.pi * 100 * 0.02 / 4 ** 2
    assert img.mean() == pytest.approx(expected, rel=0.01)


def test_envmap_top_row_is_up(exp_of, tmp_path):
    img = np.zeros((16, 32, 3), np.float32)
    img[:4] = 1.0  # only the top rows are bright
    io.write_rgb_exr(tmp_path / "top.exr", img)
    d = experiment()
    d["scene"]["emitters"] = [{"type": "envmap", "file": "top.exr", "scale": 2}]
    scene = build_scene(exp_of(d))
    env = scene.mi_scene.environment()

    def radiance(direction):
        si = dr.zeros(mi.SurfaceInteraction3f)
        si.wi = -mi.Vector3f(direction)
        return np.array(env.eval(si)).ravel()
    assert np.allclose(radiance([0, 0, 1]), 2) and np.allclose(radiance([0, 0, -1]), 0)
    assert np.allclose(radiance([1, 0, 0]), 0)


def test_mesh_file_round_trip(exp_of, tmp_path):
    V, F = meshes.torus(1, 0.25, 12, 6)
    meshes.write_ply(tmp_path / "torus.ply", V, F)
    d = experiment()
    d["scene"]["objects"][0]["mesh"] = {"file": "torus.ply"}
    scene = build_scene(exp_of(d))
    assert np.allclose(scene.objects["ball"].vertices, V + [0, 0, 0.5])
    assert np.array_equal(scene.objects["ball"].faces, F)


def test_uv_sphere_resolution_and_seam_welding(tmp_path):
    V, F = meshes.sphere(1.0, resolution=8)
    assert not meshes.degenerate_faces(V, F).any()
    assert np.allclose(np.linalg.norm(V, axis=1), 1.0)
    # a cube whose faces each have their own vertices (as OBJ seams) is welded back to 8 vertices
    Vc, Fc = meshes.cube((1, 1, 1))
    meshes.write_ply(tmp_path / "split.ply", Vc[Fc.reshape(-1)], np.arange(36).reshape(-1, 3))
    from psdr_cli.config.objects import MeshSpec
    V2, F2 = meshes.load_mesh(MeshSpec("m", file=tmp_path / "split.ply"), "x.yaml")
    assert len(V2) == 8 and len(F2) == 12


def test_the_bunny_is_decimated_once_per_process_and_handed_out_as_copies():
    """meshes.bunny remembers the decimated sample (a run builds it for its targets, scene and
    evaluation): the second call decimates nothing, and a caller's edits do not reach the next."""
    meshes.decimated_bunny.cache_clear()
    V, F = meshes.bunny(0.8, 300)
    V[:] = 0.0
    F[:] = 0
    V2, F2 = meshes.bunny(0.8, 300)
    info = meshes.decimated_bunny.cache_info()
    assert info.misses == 1 and info.hits == 1
    assert np.ptp(V2, axis=0).max() == pytest.approx(0.8) and F2.max() == len(V2) - 1
