"""Reconstruction from photographs (optimize.target.dataset): the shipped example dataset (rendered
by Mitsuba's own path integrator, not by psdr) end to end, the normalised frame, the formats
agreeing, the visual hull's topology, held-out scores and one-line errors."""
import copy
import json
import shutil
import warnings
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest
import trimesh
import yaml
from scipy.ndimage import binary_dilation, binary_erosion
from skimage.metrics import structural_similarity

from psdr_cli import api
from psdr_cli.datasets.views import View
from psdr_cli.errors import PsdrError, PsdrWarning
from psdr_cli.scoring.held_out import psnr, score_view, ssim
from psdr_cli.experiment.dataset_frame import look_at_point, to_dataset, to_normalised
from psdr_cli.experiment.load import load_experiment, parse_experiment
from psdr_cli.support import backend
from psdr_cli.target_sources import visual_hull as visual_hull_module
from psdr_cli.target_sources.visual_hull import MAX_RESOLUTION, grid_resolution, mask_distance, visual_hull
from conftest import run_cli

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "data" / "photo_bunny"
EXAMPLE = ROOT / "configs" / "photos" / "bunny_blender.yaml"


def experiment_data(dataset: Path, **optimize) -> dict:
    """The example experiment with absolute paths, on ``dataset``, at test scale."""
    data = yaml.safe_load(EXAMPLE.read_text())
    data["scene"]["emitters"][0]["file"] = str(ROOT / "scenes" / "studio.exr")
    data["optimize"]["target"]["dataset"] = {"path": str(dataset)}
    # the poses are exact here, and kept (pose refinement, on by default for datasets: test_camera_refinement.py)
    data["optimize"].update({"iterations": 4, "batch_size": 2, "checkpoint_every": 2, "preview_views": [0],
                             "remesh": {"method": "none"}, "cameras": "off", **optimize})
    return data


def write(tmp_path, data, name="photos.yaml") -> Path:
    data = copy.deepcopy(data)
    data["output"] = str(tmp_path / "runs")
    path = tmp_path / name
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def moved_blender_dataset(src: Path, dst: Path, scale: float, shift) -> Path:
    """A copy of a Blender dataset whose world is x ↦ scale·x + shift."""
    shutil.copytree(src, dst)
    for f in dst.glob("transforms_*.json"):
        d = json.loads(f.read_text())
        for frame in d["frames"]:
            M = np.array(frame["transform_matrix"])
            M[:3, 3] = scale * M[:3, 3] + np.asarray(shift)
            frame["transform_matrix"] = M.tolist()
        f.write_text(json.dumps(d))
    return dst


def test_the_example_dataset_reconstructs_and_is_scored_on_held_out_views(tmp_path, run_psdr):
    """`psdr optimize` (a real process) then `psdr evaluate` (in this process) on the shipped
    example: meshes in the dataset's own coordinates (the first one, the visual hull, already
    close to the ground truth), held-out scores for the initial and the last mesh, a strip per
    held-out view."""
    config = write(tmp_path, experiment_data(DATA / "blender", iterations=12, checkpoint_every=6))
    r = run_cli("optimize", config, timeout=400)
    assert r.returncode == 0, r.stdout + r.stderr
    run = tmp_path / "runs" / "photos_bunny_blender"
    r = run_psdr("evaluate", config, "--reference", DATA / "ground_truth.ply")
    assert r.returncode == 0, r.stdout + r.stderr
    rows = json.loads((run / "held_out" / "held_out.json").read_text())["meshes"]
    assert [row["iteration"] for row in rows] == [0, 12]
    for row in rows:
        assert row["views"] == 4 and row["iou"] > 0.9 and row["psnr"] > 15, row
        assert row["chamfer_l1"] < 0.03, row  # the hull, in the dataset's frame (not the normalised one)
    first, last = rows
    # no step away: the IoU may jitter, not drop. Over seeds 0-3, 12 iterations moved it by -0.0052
    # to +0.0010 on the tree before issue 38's batched views and by -0.0063 to +0.0023 after (the
    # 0.005 used before failed seed 1 of the earlier tree too); the PSNR rose in all eight runs
    assert last["iou"] >= first["iou"] - 0.01 and last["psnr"] > first["psnr"], rows
    assert len(list((run / "held_out").glob("*.png"))) == 8


def test_a_dataset_scaled_and_shifted_gives_the_same_reconstruction_scaled_and_shifted(tmp_path):
    """The normalised frame depends on the cameras alone: the same photographs with the world
    x ↦ 100·x + 1000 give the same meshes, mapped the same way."""
    finals = []
    for name, scale, shift in (("a", 1.0, (0, 0, 0)), ("b", 100.0, (1000.0, 1000.0, 1000.0))):
        dataset = moved_blender_dataset(DATA / "blender", tmp_path / name / "data", scale, shift)
        config = write(tmp_path / name, experiment_data(dataset, iterations=3), "photos.yaml")
        api.optimize(load_experiment(config), warn=lambda line: None)
        finals.append(trimesh.load(tmp_path / name / "runs" / "photos_bunny_blender" / "final.ply", process=False))
    a, b = (np.asarray(m.vertices, np.float64) for m in finals)
    assert a.shape == b.shape and np.array_equal(finals[0].faces, finals[1].faces)
    size = np.ptp(a, axis=0).max()
    assert np.abs((b - 1000.0) / 100.0 - a).max() < 1e-3 * size


def test_the_blender_and_colmap_forms_of_a_dataset_give_the_same_cameras(tmp_path):
    """The example's COLMAP text model (JPEGs over a backdrop, mask PNGs) and its Blender form
    (RGBA PNGs) describe the same cameras: the same normalised cameras, film and hidden
    background (every 5th view held out of the COLMAP form: the Blender form's test split)."""
    blender = load_experiment(write(tmp_path, experiment_data(DATA / "blender")))
    data = experiment_data(DATA / "colmap")
    data["optimize"]["target"]["dataset"]["holdout_every"] = 5
    colmap = parse_experiment(data, tmp_path / "colmap.yaml")
    assert (blender.scene.width, blender.scene.height) == (colmap.scene.width, colmap.scene.height) == (64, 64)
    assert blender.scene.hide_background and colmap.scene.hide_background
    # the Blender form's train split and COLMAP's with holdout_every 5: the views i % 5 != 0
    b = {i: c for i, c in zip([i for i in range(20) if i % 5 != 0], blender.scene.cameras)}
    c = {i: cam for i, cam in zip([i for i in range(20) if i % 5 != 0], colmap.scene.cameras)}
    assert set(b) == set(c)
    fb, fc = blender.optimize.target_dataset.frame, colmap.optimize.target_dataset.frame
    for i in set(b) & set(c):
        ob = to_dataset(np.array([b[i].origin]), fb)[0]
        oc = to_dataset(np.array([c[i].origin]), fc)[0]
        assert np.allclose(ob, oc, atol=1e-4), (i, ob, oc)
        assert b[i].fov == pytest.approx(c[i].fov, abs=1e-4)
        assert np.allclose(b[i].principal_point, c[i].principal_point, atol=1e-6)
    # the targets agree where the L1 sees them: a JPEG over a backdrop with a mask file against an
    # RGBA PNG, premultiplied; the COLMAP form's partly covered pixels (its colour mixes in the
    # backdrop) are left out of its L1 (weight 0)
    from psdr_cli.target_sources.camera_dataset import dataset_masks, dataset_targets
    tb, vb = dataset_targets(blender)
    tc, vc = dataset_targets(colmap)
    weights = dataset_masks(colmap, vc).weights
    tb = dict(zip(b, tb))
    for (i, target), w in zip(zip(c, tc), weights):
        if i in tb:
            assert np.abs(target - tb[i])[w > 0].mean() < 0.01, i
            assert (w == 0).sum() > 20  # the silhouette's partly covered pixels


def test_the_look_at_point_and_the_normalised_frame():
    origins = np.array([[2.0, 0, 1], [0, 2.0, 1], [-2.0, 0, 1], [0, -2.0, 1]])
    axes = -origins / np.linalg.norm(origins, axis=1, keepdims=True)
    assert np.allclose(look_at_point(origins, axes), 0.0, atol=1e-9)
    assert look_at_point(origins, np.tile([1.0, 0, 0], (4, 1))) is None  # parallel axes: none
    frame = (0.25, (1.0, 2.0, 3.0))
    V = np.random.default_rng(0).normal(size=(10, 3))
    assert np.allclose(to_dataset(to_normalised(V, frame), frame), V)


def ray_hits(mesh, origin, directions) -> np.ndarray:
    """Whether rays from ``origin`` along ``directions`` hit ``mesh`` (Mitsuba's ray tracer)."""
    backend.select_variant("auto")
    shape = mi.Mesh("m", len(mesh.vertices), len(mesh.faces))
    params = mi.traverse(shape)
    params["vertex_positions"] = mi.Float(np.ravel(mesh.vertices).astype(np.float32))
    params["faces"] = mi.UInt32(np.ravel(mesh.faces).astype(np.uint32))
    params.update()
    scene = mi.load_dict({"type": "scene", "m": shape})
    d = mi.Vector3f(*(mi.Float(directions[:, k].astype(np.float32)) for k in range(3)))
    ray = mi.Ray3f(mi.Point3f(*(float(x) for x in origin)), dr.normalize(d))
    return np.asarray(scene.ray_intersect(ray).is_valid())


def torus_views(count=12, size=40):
    """Views of a torus (major radius 0.6, minor 0.2) on a ring above it, masks by ray casting."""
    torus = trimesh.creation.torus(major_radius=0.6, minor_radius=0.2, major_sections=48, minor_sections=16)
    return mesh_views(torus, count, size)


def mesh_views(mesh, count=12, size=40):
    """Views of ``mesh`` from a ring of cameras 3 units from the origin, alternately 35° and 70°
    above it (a 40° field of view), masks by ray casting."""
    views = []
    f = size / (2 * np.tan(np.radians(20)))
    for i in range(count):
        a, e = 2 * np.pi * i / count, np.radians(35 if i % 2 else 70)
        origin = 3.0 * np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
        forward = -origin / np.linalg.norm(origin)
        right = np.cross(forward, [0, 0, 1.0])
        right /= np.linalg.norm(right)
        M = np.eye(4)
        M[:3, 0], M[:3, 1], M[:3, 2], M[:3, 3] = right, np.cross(forward, right), forward, origin
        u, v = np.meshgrid(np.arange(size) + 0.5, np.arange(size) + 0.5)
        d = np.stack([(u - size / 2) / f, (v - size / 2) / f, np.ones_like(u)], -1).reshape(-1, 3) @ M[:3, :3].T
        hit = ray_hits(mesh, origin, d)
        views.append(View(f"v{i}", np.zeros((size, size, 3)), hit.reshape(size, size).astype(float), M,
                          f, f, size / 2, size / 2, size, size, "train"))
    return views


def test_the_visual_hull_of_a_torus_keeps_its_hole():
    """Carved from masks, the initial shape of a torus is one closed surface of genus 1 (Euler
    characteristic 0), not a sphere."""
    V, F = visual_hull(torus_views())
    mesh = trimesh.Trimesh(V, F, process=True)
    assert mesh.is_watertight
    assert mesh.euler_number == 0, mesh.euler_number
    assert 0.7 < np.ptp(V[:, 0]) < 1.8 and np.ptp(V[:, 2]) < 0.9


def test_the_visual_hull_keeps_a_part_two_pixels_wide():
    """A ball on a rod 2.6 pixels wide seen from 16 views of 96²: the carving grid's cell is about
    a pixel (72 points a side would be two pixels a cell and lose the rod), so the hull reaches
    down to the rod's end."""
    ball = trimesh.creation.icosphere(subdivisions=3, radius=0.4)
    ball.apply_translation([0, 0, 0.3])
    rod = trimesh.creation.cylinder(radius=0.03, height=0.9, sections=24)
    rod.apply_translation([0, 0, -0.4])
    views = mesh_views(trimesh.util.concatenate([ball, rod]), count=16, size=96)
    assert grid_resolution(views, 1.5) == MAX_RESOLUTION
    V, _ = visual_hull(views)
    assert V[:, 2].min() < -0.7, V[:, 2].min()


def silhouette(V, F, view) -> np.ndarray:
    """(H, W) whether the ray through each pixel's centre of ``view`` hits the mesh (V, F)."""
    size = view.mask.shape
    u, v = np.meshgrid(np.arange(size[1]) + 0.5, np.arange(size[0]) + 0.5)
    d = np.stack([(u - view.cx) / view.fx, (v - view.cy) / view.fy, np.ones_like(u)], -1).reshape(-1, 3)
    M = view.cam_to_world
    return ray_hits(trimesh.Trimesh(V, F, process=False), M[:3, 3], d @ M[:3, :3].T).reshape(size)


def test_the_visual_hull_projects_inside_every_views_mask_and_covers_it():
    """Per view, the hull's silhouette (rays through pixel centres) lies inside that view's mask,
    up to one pixel: the surface runs between a carved and a kept voxel centre and is then smoothed,
    and a voxel (3/71 wide) spans 0.8 px at the torus's distance. And it covers the mask up to one
    pixel: the hull holds the object. A hull that ignores the mask of one of the low views has 8–9
    silhouette pixels beyond that view's dilated mask (measured); the true hull has none."""
    views = torus_views()
    V, F = visual_hull(views)
    for view in views:
        hull, mask = silhouette(V, F, view), view.mask >= 0.5
        assert not (hull & ~binary_dilation(mask)).any(), view.name
        assert not (binary_erosion(mask) & ~hull).any(), view.name


def turned_views(views, pixels: float, seed: int = 3):
    """``views`` with each camera turned about its own centre by ``pixels`` (at its focal
    length) about a random axis: poses as slightly wrong as a capture's, masks kept."""
    rng = np.random.default_rng(seed)
    out = []
    for view in views:
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        angle = pixels / view.fx
        K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
        M = view.cam_to_world.copy()
        M[:3, :3] = (np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K) @ M[:3, :3]
        out.append(copy.copy(view))
        out[-1].cam_to_world = M
    return out


def test_the_visual_hull_of_slightly_wrong_cameras_keeps_the_object():
    """Cameras turned by 2 px make the masks disagree: carved exactly, the torus's tube is cut
    (its silhouette through the true cameras leaves 500-odd pixels of the eroded masks uncovered,
    measured); the hull carved with the margin found from the masks (with one warning) leaves
    under a tenth of that (20, measured), and consistent masks get no margin (the same hull as
    before, no warning)."""
    truth = torus_views()
    wrong = turned_views(truth, 2.0)

    def lost(V, F):
        return sum(int((binary_erosion(t.mask >= 0.5) & ~silhouette(V, F, t)).sum()) for t in truth)

    exact = lost(*visual_hull(wrong, margin=0))
    assert exact > 100
    with pytest.warns(PsdrWarning, match="masks disagree by about"):
        V, F = visual_hull(wrong)
    assert lost(V, F) < exact / 10
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        V0, F0 = visual_hull(truth)
    V1, F1 = visual_hull(truth, margin=0)
    assert np.array_equal(V0, V1) and np.array_equal(F0, F1)


def test_a_view_with_an_empty_mask_sees_every_point_infinitely_far_from_it(monkeypatch):
    """No margin keeps a point that a view with an empty mask sees (its distance to the mask is
    +∞, not the distance to the image's corner); masks that no margin explains get the largest
    margin, and the warning says "more than" (here no hull may leave anything uncovered)."""
    views = torus_views(count=4)
    empty = copy.copy(views[0])
    empty.mask = np.zeros_like(views[0].mask)
    points = np.array([[0.6, 0.0, 0.0], [0.0, 0.0, 5.0]])
    assert np.isinf(mask_distance(points, [empty])).all()
    monkeypatch.setattr(visual_hull_module, "LOST_WIDTH", -1.0)
    with pytest.warns(PsdrWarning, match="more than 8 px"):
        visual_hull(turned_views(torus_views(), 2.0))


def test_held_out_scores():
    backend.select_variant("auto")
    rng = np.random.default_rng(1)
    target = rng.uniform(0.2, 0.8, (16, 16, 3))
    assert psnr(target, target) == float("inf")
    assert psnr(target + 0.1, target) == pytest.approx(20.0, abs=1e-6)
    assert ssim(target, target) == pytest.approx(1.0)
    mask = np.zeros((16, 16))
    mask[4:12, 4:12] = 1.0
    covered = np.zeros((16, 16))
    covered[4:12, 4:8] = 1.0
    score = score_view("v", target, target, mask, covered)
    assert score.iou == pytest.approx(0.5)


def test_ssim_is_the_fields_ssim_and_sees_what_differs():
    """held_out.ssim (Gaussian window σ = 1.5, the constants of Wang et al. 2004 with data range 1)
    against scikit-image's own mean over the pixels it keeps (5 px from the border) on perturbed
    images; in closed form on two flat images, where the window sees no contrast and only the
    luminance term (2μₓμᵧ + C₁)/(μₓ² + μᵧ² + C₁), C₁ = 0.01², remains; lower for more noise, low for
    unrelated images, symmetric."""
    rng = np.random.default_rng(4)
    image = rng.uniform(0.2, 0.8, (40, 48, 3))
    image = (image + np.roll(image, 1, axis=0) + np.roll(image, 1, axis=1)) / 3  # some structure
    inner = np.zeros(image.shape[:2], bool)
    inner[5:-5, 5:-5] = True
    scores = []
    for noise in (0.01, 0.05, 0.2):
        noisy = np.clip(image + rng.normal(0.0, noise, image.shape), 0, 1)
        theirs = structural_similarity(noisy, image, channel_axis=-1, data_range=1.0, gaussian_weights=True,
                                       sigma=1.5, use_sample_covariance=False)
        assert ssim(noisy, image, inner) == pytest.approx(theirs, rel=1e-9, abs=1e-12)
        assert ssim(noisy, image) == pytest.approx(ssim(image, noisy), rel=1e-9)
        scores.append(ssim(noisy, image))
    assert 1.0 > scores[0] > scores[1] > scores[2]
    assert ssim(rng.uniform(0, 1, image.shape), image) < 0.2
    a, b = np.full((16, 16, 3), 0.2), np.full((16, 16, 3), 0.6)
    assert ssim(a, b) == pytest.approx((2 * 0.2 * 0.6 + 1e-4) / (0.2 ** 2 + 0.6 ** 2 + 1e-4), rel=1e-6)


def test_held_out_scores_see_the_held_out_photographs(tmp_path, run_psdr):
    """`psdr evaluate` scores the held-out split, seen by the scores and not only by their count:
    with the held-out photographs mirrored left to right (the training ones untouched) the same
    mesh scores a much lower IoU than with the true ones; scoring the training split instead
    would not see the change."""
    (tmp_path / "clean").mkdir()
    clean = write(tmp_path / "clean", experiment_data(DATA / "blender", iterations=1))
    mirrored_data = tmp_path / "mirrored" / "data"
    shutil.copytree(DATA / "blender", mirrored_data)
    frames = json.loads((mirrored_data / "transforms_test.json").read_text())["frames"]
    from PIL import Image
    for frame in frames:
        path = mirrored_data / f"{frame['file_path']}.png"
        Image.open(path).transpose(Image.Transpose.FLIP_LEFT_RIGHT).save(path)
    mirrored = write(tmp_path / "mirrored", experiment_data(mirrored_data, iterations=1))
    ious = []
    for config in (clean, mirrored):
        r = run_psdr("optimize", config)
        assert r.returncode == 0, r.stderr
        r = run_psdr("evaluate", config)
        assert r.returncode == 0, r.stderr
        run = config.parent / "runs" / "photos_bunny_blender"
        rows = json.loads((run / "held_out" / "held_out.json").read_text())["meshes"]
        ious.append(rows[0]["iou"])
    assert ious[0] > 0.9 and ious[1] < ious[0] - 0.1, ious


def test_held_out_views_keep_the_lights_mapped_once(tmp_path):
    """The held-out split of a loaded experiment moves only its cameras: an area light given in the
    dataset's coordinates is mapped into the normalised frame once, for training and held-out
    views alike."""
    from psdr_cli.experiment.dataset_frame import dataset_scene
    data = experiment_data(DATA / "blender")
    data["scene"]["emitters"].append({"type": "area", "center": [4.0, -2.0, 9.0], "normal": [0, 0, -1],
                                      "size": [2.0, 2.0], "radiance": 5.0})
    exp = load_experiment(write(tmp_path, data))
    test = dataset_scene(exp, split="test")
    assert test.scene.emitters == exp.scene.emitters
    frame = exp.optimize.target_dataset.frame
    assert np.allclose(exp.scene.emitters[1].center, to_normalised(np.array([4.0, -2.0, 9.0]), frame))
    assert exp.scene.emitters[1].size[0] == pytest.approx(2.0 * frame[0])
    assert len(test.scene.cameras) == 4 and len(exp.scene.cameras) == 16


def test_an_init_mesh_file_is_read_in_the_datasets_coordinates(tmp_path):
    """``optimize.init`` as a mesh file (e.g. another run's final.ply) is in the dataset's
    coordinates: the ground truth given as init starts where the object is (its checkpoint 0, in
    the dataset's coordinates, is the ground truth again)."""
    data = experiment_data(DATA / "blender", iterations=1)
    data["optimize"]["init"] = {"mesh": {"file": str(DATA / "ground_truth.ply")}}
    exp = load_experiment(write(tmp_path, data))
    api.optimize(exp, warn=lambda line: None)
    start = trimesh.load(exp.run_dir / "checkpoints" / "iter_0000.ply", process=False)
    truth = trimesh.load(DATA / "ground_truth.ply", process=False)
    assert np.allclose(start.vertices, truth.vertices, atol=1e-4 * np.ptp(truth.vertices))


@pytest.mark.parametrize("edit, message", [
    (lambda d: d["scene"].update(cameras=[{"origin": [0, -3, 0], "target": [0, 0, 0]}]),
     "scene.cameras: not allowed with optimize.target.dataset"),
    (lambda d: d["scene"].update(film={"width": 32, "height": 32}), "scene.film: not allowed"),
    (lambda d: d["optimize"]["target"]["dataset"].update(path="missing_folder"), "optimize.target.dataset.path: not found"),
    (lambda d: d["estimator"].update(engine="mitsuba"), "estimator.engine: 'mitsuba' cannot hide the background"),
    (lambda d: d["optimize"]["target"]["dataset"].update(holdout_every=1), "holdout_every"),
    (lambda d: d["optimize"]["target"]["dataset"].update(holdout_every=100),  # named by the experiment's key
     "photos.yaml: optimize.target.dataset.holdout_every: 100 is not usable (expected an integer from 2 to 20"),
    (lambda d: d["optimize"]["target"]["dataset"].update(downsample=100),
     "photos.yaml: optimize.target.dataset.downsample: 100 is not usable (expected an integer from 1 to 64"),
    (lambda d: d["optimize"]["target"].update(mesh={"shape": "sphere"}), "give one of 'images', 'mesh' and 'dataset'"),
    (lambda d: d["optimize"].update(variants=[{"label": "m", "engine": "mitsuba"}]), "'mitsuba' cannot hide"),
    (lambda d: d["scene"]["objects"].append({"name": "stand", "mesh": {"shape": "plane"}}),
     "'stand' would show against the black"),
])
def test_bad_dataset_experiments_are_one_line(tmp_path, edit, message):
    data = experiment_data(DATA / "blender")
    edit(data)
    with pytest.raises(PsdrError) as err:
        api.optimize(load_experiment(write(tmp_path, data)))
    assert message in str(err.value) and "\n" not in str(err.value)
    assert not (tmp_path / "runs").exists()


def test_a_bad_dataset_experiment_is_one_line_from_the_command_line(tmp_path, run_psdr):
    data = experiment_data(DATA / "blender")
    data["scene"]["film"] = {"width": 32, "height": 32}
    r = run_psdr("optimize", write(tmp_path, data))
    assert r.returncode == 2, r.stdout + r.stderr
    lines = [line for line in r.stderr.strip().splitlines() if line]
    assert len(lines) == 1 and "scene.film: not allowed with optimize.target.dataset" in lines[0], r.stderr
    assert not (tmp_path / "runs").exists()


def edited_blender(tmp_path, name, edit_frame=None, edit_image=None) -> Path:
    """A copy of the example's Blender form with its frames and/or images edited."""
    import cv2
    dataset = tmp_path / name
    shutil.copytree(DATA / "blender", dataset)
    for f in dataset.glob("transforms_*.json"):
        d = json.loads(f.read_text())
        for i, frame in enumerate(d["frames"]):
            if edit_frame:
                edit_frame(i, frame)
            if edit_image:
                path = dataset / (frame["file_path"] + ".png")
                cv2.imwrite(str(path), edit_image(i, cv2.imread(str(path), cv2.IMREAD_UNCHANGED)))
        f.write_text(json.dumps(d))
    return dataset


def test_a_dataset_of_cameras_looking_outward_is_one_line(tmp_path):
    """Every camera turned 180° about its up axis (its axis through the same common point, but
    facing away): refused, not a silent sphere behind every camera."""
    def turn(i, frame):
        M = np.array(frame["transform_matrix"])
        M[:3, 0], M[:3, 2] = -M[:3, 0], -M[:3, 2]
        frame["transform_matrix"] = M.tolist()
    with pytest.raises(PsdrError, match="look away from"):
        parse_experiment(experiment_data(edited_blender(tmp_path, "outward", turn)), tmp_path / "x.yaml")


def test_masks_on_some_photographs_only_are_one_line(tmp_path):
    import cv2
    dataset = edited_blender(tmp_path, "mixed", edit_image=lambda i, im: cv2.cvtColor(im, cv2.COLOR_BGRA2BGR)
                             if i == 2 else im)
    with pytest.raises(PsdrError, match="has no mask"):
        parse_experiment(experiment_data(dataset), tmp_path / "x.yaml")


def test_an_opaque_alpha_everywhere_is_not_a_mask(tmp_path):
    def opaque(i, im):
        im[..., 3] = 255
        return im
    exp = parse_experiment(experiment_data(edited_blender(tmp_path, "opaque", edit_image=opaque)), tmp_path / "x.yaml")
    with pytest.raises(PsdrError, match="opaque everywhere"):
        api.optimize(exp)


def test_a_dataset_whose_cameras_share_no_look_at_point_is_one_line(tmp_path):
    dataset = tmp_path / "parallel"
    shutil.copytree(DATA / "blender", dataset)
    for f in dataset.glob("transforms_*.json"):
        d = json.loads(f.read_text())
        for i, frame in enumerate(d["frames"]):
            frame["transform_matrix"] = [[1, 0, 0, float(i)], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
        f.write_text(json.dumps(d))
    with pytest.raises(PsdrError, match="no common look-at point"):
        parse_experiment(experiment_data(dataset), tmp_path / "x.yaml")


def distorted_transforms_dataset(src: Path, dst: Path, k1=-0.35, k2=0.0) -> Path:
    """The example's training views as a nerfstudio ``transforms.json`` with OPENCV distortion:
    each RGBA photograph warped by the lens model (OpenCV's undistortPoints gives, for every
    pixel of the distorted image, where it samples the pinhole image)."""
    import cv2
    dst.mkdir(parents=True)
    blender = json.loads((src / "transforms_train.json").read_text())
    size = 64
    f = size / (2 * np.tan(blender["camera_angle_x"] / 2))
    K = np.array([[f, 0, size / 2 - 0.5], [0, f, size / 2 - 0.5], [0, 0, 1]])
    dist = np.array([k1, k2, 0.0, 0.0])
    u, v = np.meshgrid(np.arange(size, dtype=np.float32), np.arange(size, dtype=np.float32))
    pts = cv2.undistortPoints(np.stack([u, v], -1).reshape(-1, 1, 2), K, dist, P=K).reshape(size, size, 2)
    frames = []
    for i, frame in enumerate(blender["frames"][:8]):
        image = cv2.imread(str(src / (frame["file_path"] + ".png")), cv2.IMREAD_UNCHANGED)
        warped = cv2.remap(image, pts[..., 0], pts[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        cv2.imwrite(str(dst / f"f{i}.png"), warped)
        frames.append({"file_path": f"f{i}.png", "transform_matrix": frame["transform_matrix"]})
    (dst / "transforms.json").write_text(json.dumps({
        "camera_model": "OPENCV", "fl_x": f, "fl_y": f, "cx": size / 2, "cy": size / 2, "w": size, "h": size,
        "k1": k1, "k2": k2, "p1": 0.0, "p2": 0.0, "frames": frames}))
    return dst


def test_a_distorted_capture_is_undistorted_once_into_the_run_folder(tmp_path, run_psdr):
    """A nerfstudio dataset with OPENCV distortion (k1 = −0.35): the photographs are undistorted
    into ``targets/undistorted/`` once (a second load reuses the files), and the undistorted
    masks agree with psdr's render of the ground truth through the new pinhole cameras (mask IoU
    ≥ 0.97 per view; the distorted masks through the original pinhole cameras reach only ~0.94)."""
    from psdr_cli.scoring.held_out import coverage
    from psdr_cli.experiment.dataset_frame import to_normalised
    from psdr_cli.scene.build import build_scene
    from psdr_cli.scene.meshes import read_mesh_file
    from psdr_cli.target_sources.camera_dataset import dataset_targets
    dataset = distorted_transforms_dataset(DATA / "blender", tmp_path / "distorted")
    data = experiment_data(dataset, iterations=1)
    data["optimize"]["target"]["dataset"]["holdout_every"] = 4
    config = write(tmp_path, data)
    r = run_psdr("optimize", config)
    assert r.returncode == 0, r.stdout + r.stderr
    cache = tmp_path / "runs" / "photos_bunny_blender" / "targets" / "undistorted"
    files = sorted(cache.glob("*.exr"))
    assert len(files) == 6  # the training views (the held-out ones at `psdr evaluate`)
    stamps = [p.stat().st_mtime_ns for p in files]
    exp = load_experiment(config)
    backend.activate(exp)
    _, views = dataset_targets(exp)
    assert [p.stat().st_mtime_ns for p in sorted(cache.glob("*.exr"))] == stamps  # reused, not rewritten
    V, F = read_mesh_file(DATA / "ground_truth.ply")
    scene = build_scene(exp, objects={"object": (to_normalised(V, exp.optimize.target_dataset.frame), F)})
    for v, view in enumerate(views):
        rendered, mask = coverage(scene, "object", v, 16) >= 0.5, view.mask >= 0.5
        assert (rendered & mask).sum() / (rendered | mask).sum() >= 0.97, v


def test_a_y_up_dataset_finds_its_up_axis_and_turns_the_environment_with_it(tmp_path):
    """The example's world turned so that its up axis is +y (x ↦ R x, R: −90° about x): the up
    axis found from the cameras is +y, the environment map's zenith follows it, and psdr's render
    of the turned ground truth equals the render of the original (the same photographs)."""
    from psdr_cli.experiment.dataset_frame import to_normalised, world_up
    from psdr_cli.rendering.render import render_view
    from psdr_cli.scene.build import build_scene
    from psdr_cli.scene.meshes import read_mesh_file
    R = np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]])  # z → y
    dataset = tmp_path / "y_up"
    shutil.copytree(DATA / "blender", dataset)
    for f in dataset.glob("transforms_*.json"):
        d = json.loads(f.read_text())
        for frame in d["frames"]:
            M = np.array(frame["transform_matrix"])
            M[:3, :3], M[:3, 3] = R @ M[:3, :3], R @ M[:3, 3]
            frame["transform_matrix"] = M.tolist()
        f.write_text(json.dumps(d))
    V, F = read_mesh_file(DATA / "ground_truth.ply")
    images = []
    for folder, vertices in ((DATA / "blender", V), (dataset, V @ R.T)):
        exp = load_experiment(write(tmp_path, experiment_data(folder), f"{folder.name}.yaml"))
        backend.activate(exp)
        scene = build_scene(exp, objects={"object": (to_normalised(vertices, exp.optimize.target_dataset.frame), F)})
        images.append(render_view(scene, 0, 64, seed=1))
        if folder == dataset:
            assert exp.scene.emitters[0].up == (0.0, 1.0, 0.0)
    assert np.abs(images[0] - images[1]).mean() < 0.01 * images[0].mean()
    assert world_up([], (0, 0, 2)) == (0.0, 0.0, 1.0)


def with_alpha(dataset: Path, split: str, change) -> Path:
    """``dataset`` (a Blender dataset) with ``change(index, alpha) -> alpha`` applied to the alpha of
    every image of ``split``."""
    from PIL import Image
    frames = json.loads((dataset / f"transforms_{split}.json").read_text())["frames"]
    for i, frame in enumerate(frames):
        path = dataset / f"{frame['file_path']}.png"
        rgba = np.asarray(Image.open(path).convert("RGBA")).copy()
        rgba[..., 3] = change(i, rgba[..., 3])
        Image.fromarray(rgba).save(path)
    return dataset


@pytest.mark.parametrize("change, index, what", [
    (lambda i, a: np.zeros_like(a) if i == 2 else a, 2, "empty"),
    (lambda i, a: np.full_like(a, 255) if i == 1 else a, 1, "covers the whole image"),
    (lambda i, a: 255 - a, 0, "looks inverted: in 16 of 16 views"),
], ids=["one-empty", "one-full", "inverted"])
def test_masks_that_cannot_be_right_are_refused_by_view(tmp_path, change, index, what):
    """One view's empty mask carved the hull to a fragment (first loss 9× the clean run's), inverted
    masks gave a hull twice the object's size: refused in one line naming the view."""
    from psdr_cli.target_sources.camera_dataset import dataset_views
    dataset = shutil.copytree(DATA / "blender", tmp_path / "data")
    with_alpha(dataset, "train", change)
    exp = load_experiment(write(tmp_path, experiment_data(dataset)))
    with pytest.raises(PsdrError) as info:
        dataset_views(exp)
    message = str(info.value)
    name = json.loads((dataset / "transforms_train.json").read_text())["frames"][index]["file_path"].lstrip("./")
    assert "transforms_train.json" in message and f"frame {name} mask" in message and what in message
    assert "\n" not in message


def test_a_corrupt_photograph_is_one_line_and_libpng_says_nothing_of_its_own(tmp_path, run_psdr):
    """A PNG whose compressed data is damaged: libpng's own complaint ("libpng error: ...") went to
    the terminal before psdr's line; it is now part of that one line."""
    dataset = shutil.copytree(DATA / "blender", tmp_path / "data")
    path = dataset / "train" / "r_001.png"
    data = bytearray(path.read_bytes())
    data[200:260] = b"\x13" * 60  # inside the image data
    path.write_bytes(bytes(data))
    r = run_psdr("optimize", write(tmp_path, experiment_data(dataset, iterations=1)))
    lines = [line for line in r.stderr.splitlines() if line.strip()]
    assert r.returncode == 2 and len(lines) == 1, r.stderr
    assert "r_001.png" in lines[0] and "cannot be decoded (libpng error" in lines[0]


def test_photographs_too_large_for_the_film_name_the_photograph_and_the_downsampling(tmp_path, run_psdr):
    """Image headers claiming 20000² were blamed on optimize.target.spp, a key the user never set."""
    dataset = shutil.copytree(DATA / "blender", tmp_path / "data")
    for path in dataset.rglob("*.png"):
        data = bytearray(path.read_bytes())
        data[16:24] = (20000).to_bytes(4, "big") * 2  # the IHDR width and height
        path.write_bytes(bytes(data))
    r = run_psdr("optimize", write(tmp_path, experiment_data(dataset, iterations=1)))
    assert r.returncode == 2 and "target.spp" not in r.stderr, r.stderr
    assert "20000×20000 pixels (by the image header)" in r.stderr
    assert "set optimize.target.dataset.downsample to 3 or more in" in r.stderr
