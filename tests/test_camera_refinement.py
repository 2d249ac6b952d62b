"""``optimize.cameras``: the pose corrections of every view (psdr_cli/optimisation/camera_refinement.py).

The derivative the loop takes of a view's image with respect to its correction is the reverse
mode of the same estimators that ``psdr grad`` runs in forward mode for ``parameter: {camera: i,
kind: rotate|translate}``, which tests/test_real_mesh_gradients.py checks against finite
differences. Here the two modes are compared on the same samples, per view, per term, for the
whole image and per tile. With Q the camera's axes, c the look-at point, o the camera's centre,
d = |o − c|, G_rot(a) and G_tr(a) the forward derivatives of Σ w·I_v for a rotation about axis a
through o and a translation along a:

    ∂(Σ w·I_v)/∂r_i = G_rot(Q e_i),   ∂(Σ w·I_v)/∂τ_i = d · G_tr(Q e_i).
"""
from __future__ import annotations

import json
import shutil
import math
from dataclasses import replace
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from psdr_cli import api
from psdr_cli.config.parameter import ParameterConfig
from psdr_cli.config.unknowns import CamerasUnknown
from psdr_cli.datasets.views import read_frames
from psdr_cli.errors import PsdrError
from psdr_cli.estimators.boundary_sampling import edge_list
from psdr_cli.scoring import held_out_alignment
from psdr_cli.scoring.held_out import score_mesh
from psdr_cli.scoring.held_out_focal import refocused_held_out
from psdr_cli.experiment.dataset_frame import dataset_scene
from psdr_cli.experiment.load import load_experiment
from psdr_cli.geometry.parameters import Parameter
from psdr_cli.optimisation.camera_refinement import CameraCorrections, gauge_basis, rotation_matrices, with_camera_mode, without_gauge
from psdr_cli.rendering.camera_motion import with_all_edges
from psdr_cli.rendering.estimate import Settings, forward_gradient, prepare, term_image, term_passes, term_seed
from psdr_cli.rendering.reference import agreement, fd_resolution, finite_difference
from psdr_cli.rendering.render import render_view
from psdr_cli.run_folder.refined_cameras import refined_poses, similarity, transforms_document, write_colmap_text
from psdr_cli.run_folder.state import State
from psdr_cli.scene.build import build_scene
from psdr_cli.support import backend
from psdr_cli.support.jitarray import jit_array
from psdr_cli.support.verdict import agrees, describe
from standins import load, tile_weights, two_camera_cfg

TERMS = ("interior", "primary", "direct")


@pytest.fixture(autouse=True, scope="module")
def variant():
    backend.select_variant("auto")


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    exp = load(two_camera_cfg(), tmp_path_factory.mktemp("cams"))
    scene = with_all_edges(build_scene(exp))
    edges = edge_list(scene, exp.estimator, Settings.from_experiment(exp).edge_sort)
    return exp, scene, edges, Settings.from_experiment(exp)


def reverse_gradients(scene, edges, settings, view: int, term: str, weights: list, image_view: int | None = None):
    """[∂(Σ w·I)/∂x for each w]: x = (r, τ) of every view, as (views, 6)."""
    image_view = view if image_view is None else image_view
    width, height = scene.resolution
    spp = term_passes(term, settings, width * height)[0]
    params = mi.traverse(scene.mi_scene)
    out = []
    for w in weights:
        cams = CameraCorrections(CamerasUnknown(mode="on"), params, len(scene.sensors), {})
        cams.attached = True
        cams.write(params)
        params.update()
        image = term_image(scene, edges, image_view, term, spp, term_seed(settings, image_view, 0, term), settings)
        loss = dr.sum(image * jit_array(mi.Float, w.ravel()))
        dr.backward(loss)
        out.append(np.concatenate([np.asarray(dr.grad(cams.opt[p]), np.float64).reshape(-1, 3)
                                   for p in ("rotation", "translation")], 1))
        cams.detach(params)
        params.update()
    return out, cams


@pytest.mark.parametrize("view", [0, 1])
@pytest.mark.parametrize("term", TERMS)
def test_reverse_pose_gradient_is_the_checked_forward_one(setup, view, term):
    """Per view and term, whole image and quarters: the reverse-mode gradient of the loop's pose
    correction against the forward mode of ``psdr grad``'s camera parameter, on the same samples
    (rotation about x, y, z through the camera's centre; translation along x, y, z)."""
    exp, scene, edges, settings = setup
    width, height = scene.resolution
    weights = tile_weights(height, width)
    reverse, cams = reverse_gradients(scene, edges, settings, view, term, weights)

    def forward(kind, axis):
        parameter = Parameter(scene, ParameterConfig(kind=kind, axis=tuple(float(a) for a in axis), camera=view))
        return forward_gradient(scene, edges, parameter, view, term, settings).passes[0]

    shift = [forward("translate", e) for e in np.eye(3)]  # G_tr per world axis: G_tr(a) = Σ_k a_k G_tr(e_k)
    Q, d = cams.axes[view], cams.distances[view]
    checked = 0
    for i in range(3):
        a = Q[:, i]
        rotation = forward("rotate", a)
        translation = d * sum(x * g for x, g in zip(a, shift))
        for column, image in ((i, rotation), (3 + i, translation)):
            for w, g in zip(weights, reverse):
                expected = float((image * w).sum())
                got = g[view, column]
                bound = 2e-3 * max(abs(expected), 1e-3 * float(np.abs(image).sum()), 1e-6)
                assert abs(got - expected) <= bound, (column, got, expected)
                checked += abs(expected) > 1e-4
    # the other view's correction does not change this view's image
    assert np.abs(np.delete(reverse[0], view, axis=0)).max() == 0.0
    assert checked >= 6  # the comparisons are not all of zeros


@pytest.mark.slow
def test_the_second_views_pan_matches_finite_differences(tmp_path):
    """The second camera of the stand-in (seen from the other side and above) turned about its own
    up axis (the pan of a correction r = (0, θ, 0)): every term against finite differences under
    the shared verdict (sum and tiles), as the first camera's world-axis rotation is in
    tests/test_real_mesh_gradients.py."""
    cfg = two_camera_cfg()
    second = cfg["scene"]["cameras"][1]
    cfg["scene"]["cameras"] = [second]  # the parameter's camera is view 0 of the checks below
    forward = np.subtract(second["target"], second["origin"])
    forward /= np.linalg.norm(forward)
    up = np.array([0.0, 0.0, 1.0]) - forward[2] * forward
    cfg["parameter"] = {"camera": 0, "kind": "rotate", "axis": (up / np.linalg.norm(up)).tolist()}
    cfg["estimator"].update(spp=256, primary_spp=256, boundary_spp=256)
    exp = load(cfg, tmp_path)
    est = api.gradient_images(exp, min_passes=8)
    scene, parameter, _, _ = prepare(exp)
    fd = finite_difference(scene, parameter, 0, 0.003, 16384, seed=exp.seed, batches=8)
    resolution = fd_resolution(render_view(scene, 0, 64, seed=exp.seed), 0.003, 16384, 8)
    stats = agreement([(e.passes, e.weights) for e in est.values()], fd, resolution=resolution)
    assert agrees(stats), describe(stats)


def test_rotation_matrices_are_rodrigues_with_the_exact_derivative_at_zero():
    """R(r) against scipy's rotation vectors (small and large angles) and dR/dr at 0 = [e]×."""
    rng = np.random.default_rng(1)
    r = np.concatenate([rng.normal(size=(4, 3)) * 1e-5, rng.normal(size=(4, 3))])
    R = rotation_matrices(mi.Vector3f(*(jit_array(mi.Float, r[:, i]) for i in range(3))))
    got = np.array([[np.asarray(R[i, j]) for j in range(3)] for i in range(3)]).transpose(2, 0, 1)
    np.testing.assert_allclose(got, Rotation.from_rotvec(r).as_matrix(), atol=2e-6)
    for i in range(3):
        x = mi.Vector3f(0.0)
        dr.enable_grad(x)
        R0 = rotation_matrices(x)
        dr.forward(x[i])
        d = np.array([[float(dr.grad(R0[a, b])[0]) for b in range(3)] for a in range(3)])
        e = np.eye(3)[i]
        np.testing.assert_allclose(d, skew(e), atol=1e-6)


def skew(a) -> np.ndarray:
    return np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])


def camera_ring(n: int = 8, seed: int = 0):
    """Camera centres around the origin (look-at point) at distances 2–3."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True) * rng.uniform(2, 3, size=(n, 1))


def similarity_corrections(axes, origins, centre, omega, shift, sigma):
    """(r, τ) of every camera (axes Q_v) under the similarity x ↦ (1 + σ) R(ω)(x − c) + c + shift,
    exactly: the camera turns by R(ω) about its centre (r = Qᵀω), and its centre moves to its
    image (τ = Qᵀ(moved − o) / d)."""
    R = Rotation.from_rotvec(omega).as_matrix()
    rest = (1 + sigma) * (origins - centre) @ R.T + centre + shift - origins
    d = np.linalg.norm(origins - centre, axis=1)
    local = lambda w: np.einsum("vji,vj->vi", axes, w)  # noqa: E731
    return local(np.tile(omega, (len(origins), 1))), local(rest / d[:, None])


@pytest.mark.parametrize("parts", [("rotation", "translation"), ("translation",)])
def test_the_gauge_projection_removes_similarities_and_keeps_the_rest(parts):
    """Corrections made by a small similarity of the whole capture (rotation, shift, scale; those
    the refined parts can make) lose all but a second-order remainder; the projection is
    idempotent, orthogonal, and a random correction keeps most of its size."""
    origins = camera_ring()
    cams = CameraCorrections(CamerasUnknown(mode="on"), fake_params(origins), len(origins), {})
    rot, tr = "rotation" in parts, "translation" in parts
    G = gauge_basis(cams.axes, origins, cams.centre, cams.distances, rot, tr)
    assert G.shape[1] == 3 * rot + 4
    free = np.ones(G.shape[0], bool)
    eps = 1e-3
    r, t = similarity_corrections(cams.axes, origins, cams.centre, eps * np.array([0.3, -0.5, 0.8]) * rot,
                                  eps * np.array([1.0, 2.0, -1.0]), eps * 0.7)
    x = np.concatenate(([r.ravel()] if rot else []) + [t.ravel()])
    left = without_gauge(x, G, free)
    assert np.linalg.norm(left) < 5e-3 * np.linalg.norm(x)  # second order in eps
    y = np.random.default_rng(2).normal(size=x.shape)
    p = without_gauge(y, G, free)
    np.testing.assert_allclose(without_gauge(p, G, free), p, atol=1e-12)
    np.testing.assert_allclose(G.T @ p, 0, atol=1e-10)
    assert np.linalg.norm(p) > 0.5 * np.linalg.norm(y)


def fake_params(origins):
    """{sensor to_world: look-at transform} of cameras at ``origins`` facing the origin."""
    out = {}
    for v, o in enumerate(origins):
        out[f"@sensor_{v:03d}.to_world"] = mi.AffineTransform4f(
            mi.ScalarTransform4f().look_at(origin=o.tolist(), target=[0, 0, 0], up=[0, 0, 1]))
    return out


def test_a_runaway_or_nan_view_stops_with_one_line_naming_it():
    """A view whose gradient is NaN, and one pushed beyond max_rotation_deg, stop (their corrections
    return to the values before the step and stay); the others move on."""
    origins = camera_ring(6)
    cams = CameraCorrections(CamerasUnknown(mode="on", learning_rate=0.006, learning_rate_final=0.006, warmup=0, start=0,
                                            max_rotation_deg=2.0),
                             fake_params(origins), 6, {})
    lines = []
    for it in range(12):
        g = np.zeros((6, 3))
        g[1] = np.nan if it == 0 else 0.0
        g[3] = [0.0, 0.0, 1.0]  # pushes view 3 by about a full step (0.34°) each iteration: beyond 2°
        g[4] = [0.01, 0.0, 0.0] if it == 0 else 0.0  # one push (0.34°)
        dr.set_grad(cams.opt["rotation"], jit_array(mi.Float, g.ravel()))
        dr.set_grad(cams.opt["translation"], jit_array(mi.Float, np.zeros(18)))
        cams.step(it, 12, lines.append)
    assert [line.split(":")[1].strip() for line in lines] == ["camera 1", "camera 3"]
    assert "non-finite" in lines[0] and "beyond 2°" in lines[1]
    assert cams.stopped.tolist() == [False, True, False, True, False, False]
    values = cams.values()
    assert np.isfinite(values["camera_rotation"]).all()
    assert np.abs(values["camera_rotation"][4]).max() > 0  # a free view moved


def test_schedule_starts_late_and_ramps():
    """No step before ``start`` (default: a fifth of the run), then a linear ramp over ``warmup``
    and a linear fall to ``learning_rate_final`` at the last iteration."""
    cams = CameraCorrections(CamerasUnknown(mode="on", learning_rate=1e-3, learning_rate_final=1e-4, warmup=4),
                             fake_params(camera_ring(3)), 3, {})
    assert cams.start(100) == 20 and not cams.refining(19, 100) and cams.refining(20, 100)
    rates = [cams.learning_rate(i, 100) for i in (19, 20, 21, 23, 24, 99)]
    np.testing.assert_allclose(rates, [0.0, 2e-4, 4e-4, 8e-4, 1e-3, 1e-4], rtol=1e-12)
    assert math.isclose(cams.learning_rate(24 + 75 // 3, 100), 1e-3 - 0.9e-3 / 3)


# --------------------------------------------------------------------------------------------
# In the loop: a camera dataset, the outputs, resume, the one-line refusals
# --------------------------------------------------------------------------------------------
ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "data" / "photo_bunny"
EXAMPLE = ROOT / "configs" / "photos" / "bunny_blender.yaml"


def dataset_experiment(tmp_path, dataset=DATA / "blender", name="cams", **optimize) -> Path:
    """The example photograph experiment on ``dataset`` at test scale (32² films), written to ``tmp_path``."""
    data = yaml.safe_load(EXAMPLE.read_text())
    data["name"], data["output"] = name, str(tmp_path / "runs")
    data["scene"]["emitters"][0]["file"] = str(ROOT / "scenes" / "studio.exr")
    data["optimize"]["target"]["dataset"] = {"path": str(dataset), "downsample": 2}
    data["optimize"].update({"iterations": 6, "batch_size": 2, "checkpoint_every": 3, "preview_views": [0],
                             "remesh": {"method": "none"}, **optimize})
    path = tmp_path / f"{name}.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def mitsuba_to_world(pose, frame) -> np.ndarray:
    """The Mitsuba camera-to-world transform psdr gives an OpenCV ``pose`` of the dataset in the
    normalised frame (s, c): the rotation with x and y flipped, the centre at s(t − c)."""
    s, c = frame
    M = np.eye(4)
    M[:3, :3] = pose[:3, :3] @ np.diag([-1.0, -1.0, 1.0])
    M[:3, 3] = s * (pose[:3, 3] - np.asarray(c))
    return M


def test_refined_poses_are_the_dataset_poses_of_the_corrected_cameras():
    """No correction: the dataset's poses as they were. A correction M = ΔM M⁰ of psdr's
    normalised camera: the refined pose P is the dataset pose whose normalised Mitsuba camera is M
    (checked through the camera construction, not the formula)."""
    rng = np.random.default_rng(3)
    poses = [np.vstack([np.hstack([Rotation.random(random_state=k).as_matrix(), rng.normal(size=(3, 1))]),
                        [[0, 0, 0, 1]]]) for k in range(3)]
    frame = (2.5, (1.0, -2.0, 0.5))
    M0 = [mitsuba_to_world(C, frame) for C in poses]
    for got, want in zip(refined_poses(poses, M0, M0, frame), poses):
        np.testing.assert_allclose(got, want, atol=1e-12)
    moves = [np.eye(4) for _ in poses]
    for k, move in enumerate(moves):
        move[:3, :3] = Rotation.from_rotvec(rng.normal(size=3) * 0.02).as_matrix()
        move[:3, 3] = rng.normal(size=3) * 0.05
    corrected = [move @ m for move, m in zip(moves, M0)]
    for P, M in zip(refined_poses(poses, M0, corrected, frame), corrected):
        np.testing.assert_allclose(mitsuba_to_world(P, frame), M, atol=1e-12)


@pytest.fixture(scope="module")
def refined_run(tmp_path_factory):
    """6 iterations of the example with its poses (and focal length) refined from iteration 2 on
    (a run, and the same run stopped after 3 iterations and resumed)."""
    tmp = tmp_path_factory.mktemp("refined")
    cams = {"start": 2, "warmup": 0, "learning_rate": 0.01, "focal": True, "focal_learning_rate": 0.01}
    full = load_experiment(dataset_experiment(tmp, cameras=cams))
    api.optimize(full, warn=lambda m: None)
    part = load_experiment(dataset_experiment(tmp, name="cams_resumed", cameras=cams))
    api.optimize(part, iterations=3, warn=lambda m: None)
    api.optimize(part, iterations=6, resume=True, warn=lambda m: None)
    return full, part


def test_a_refined_run_writes_its_cameras_in_the_datasets_format(refined_run):
    """cameras.json names every training view with its refined pose (dataset coordinates, OpenCV
    axes) and its correction; refined_cameras/transforms_train.json is a Blender split psdr reads
    back to the same poses, its images the dataset's."""
    full, _ = refined_run
    run = full.run_dir
    doc = json.loads((run / "cameras.json").read_text())
    frames = read_frames({"path": DATA / "blender"})
    train = [f for f in frames if f.split == "train"]
    assert [v["name"] for v in doc["views"]] == [f.name for f in train]
    moved = [v["correction"]["rotation_deg"] for v in doc["views"]]
    assert max(moved) > 0.05 and doc["coordinates"] == "dataset" and doc["iteration"] == 6
    back = read_frames({"path": run / "refined_cameras" / "transforms_train.json"})
    assert [Path(f.image).resolve() for f in back] == [Path(f.image).resolve() for f in train]
    for f, v in zip(back, doc["views"]):
        np.testing.assert_allclose(f.cam_to_world, np.array(v["cam_to_world"]), atol=1e-9)
    summary = json.loads((run / "optimize.json").read_text())
    assert summary["values"]["cameras"] == str(run / "cameras.json")


def test_a_resumed_refinement_continues_exactly(refined_run):
    """Stopped after 3 iterations and resumed: the corrections, their Adam moments and the shape
    are the uninterrupted run's."""
    full, part = refined_run
    a, b = State.load(full.run_dir / "state.npz"), State.load(part.run_dir / "state.npz")
    for key in ("camera_rotation", "camera_translation", "camera_stopped"):
        np.testing.assert_array_equal(a.values[key], b.values[key])
    for key in ("camera_rotation", "camera_translation"):
        assert a.adam[key][0] == b.adam[key][0]
        np.testing.assert_array_equal(a.adam[key][1], b.adam[key][1])
    np.testing.assert_array_equal(a.V, b.V)


def test_a_refined_run_writes_and_resumes_its_focal_length(refined_run):
    """optimize.cameras.focal: the refined focal scale is saved (camera_focal, one camera model),
    resumed exactly with its Adam moments, and carried into cameras.json (f_x·s, focal_scale) and
    into the Blender split written back (camera_angle_x of f_x·s)."""
    full, part = refined_run
    a, b = State.load(full.run_dir / "state.npz"), State.load(part.run_dir / "state.npz")
    np.testing.assert_array_equal(a.values["camera_focal"], b.values["camera_focal"])
    assert a.adam["camera_focal"][0] == b.adam["camera_focal"][0]
    np.testing.assert_array_equal(a.adam["camera_focal"][1], b.adam["camera_focal"][1])
    s = math.exp(float(np.ravel(a.values["camera_focal"])[0]))
    assert np.ravel(a.values["camera_focal"]).shape == (1,) and s != 1.0
    doc = json.loads((full.run_dir / "cameras.json").read_text())
    train = [f for f in read_frames({"path": DATA / "blender"}) if f.split == "train"]
    for view, frame in zip(doc["views"], train):
        assert view["correction"]["focal_scale"] == pytest.approx(s, rel=1e-12)
        assert view["fx"] == pytest.approx(frame.fx * s, rel=1e-9)
    back = read_frames({"path": full.run_dir / "refined_cameras" / "transforms_train.json"})
    assert back[0].fx == pytest.approx(train[0].fx * s, rel=1e-6)


def test_the_colmap_form_of_the_refined_cameras_reads_back(tmp_path, refined_run):
    """The COLMAP text model of the refined poses, read by psdr's COLMAP reader with the images
    of the example's COLMAP form: the same poses and intrinsics."""
    full, _ = refined_run
    frames = [f for f in read_frames({"path": DATA / "colmap"})]
    doc = json.loads((full.run_dir / "cameras.json").read_text())
    poses = [np.array(v["cam_to_world"]) for v in doc["views"]][:len(frames)]
    write_colmap_text(tmp_path / "sparse" / "0", frames[:len(poses)], poses)
    back = read_frames({"path": tmp_path, "format": "colmap", "model": tmp_path / "sparse" / "0",
                        "images": DATA / "colmap" / "images"})
    for f, g, P in zip(back, frames, poses):
        assert f.name == g.name and (f.fx, f.fy, f.cx, f.cy) == pytest.approx((g.fx, g.fy, g.cx, g.cy))
        np.testing.assert_allclose(f.cam_to_world, P, atol=1e-9)


def test_the_transforms_form_of_the_refined_cameras_reads_back(tmp_path):
    """An instant-ngp / nerfstudio transforms.json of given poses, read by psdr's reader: the
    same images, poses and intrinsics (a distorted camera's coefficients included)."""
    frames = [f for f in read_frames({"path": DATA / "blender"}) if f.split == "train"][:4]
    frames[1] = replace(frames[1], distortion=(-0.1, 0.02, 0.001, -0.002))
    rng = np.random.default_rng(5)
    poses = [f.cam_to_world @ np.vstack([np.hstack([Rotation.from_rotvec(rng.normal(size=3) * 0.01).as_matrix(),
                                                    rng.normal(size=(3, 1)) * 0.01]), [[0, 0, 0, 1]]])
             for f in frames]
    out = tmp_path / "refined"
    out.mkdir()
    (out / "transforms.json").write_text(json.dumps(transforms_document(out, frames, poses)))
    back = read_frames({"path": out / "transforms.json"})
    for f, g, P in zip(back, frames, poses):
        assert Path(f.image).resolve() == Path(g.image).resolve() and f.distortion == pytest.approx(g.distortion)
        assert (f.fx, f.fy, f.cx, f.cy) == pytest.approx((g.fx, g.fy, g.cx, g.cy))
        np.testing.assert_allclose(f.cam_to_world, P, atol=1e-9)


def perturbed_test_split(src: Path, dst: Path, degrees: float, split: str = "test", seed: int = 11) -> Path:
    """A copy of a Blender dataset whose ``split`` cameras (default the held-out ones) are each
    turned by ``degrees`` about a random axis through their centre (the others exact)."""
    shutil.copytree(src, dst)
    rng = np.random.default_rng(seed)
    data = json.loads((dst / f"transforms_{split}.json").read_text())
    for frame in data["frames"]:
        M = np.array(frame["transform_matrix"])
        axis = rng.normal(size=3)
        M[:3, :3] = Rotation.from_rotvec(np.radians(degrees) * axis / np.linalg.norm(axis)).as_matrix() @ M[:3, :3]
        frame["transform_matrix"] = M.tolist()
    (dst / f"transforms_{split}.json").write_text(json.dumps(data))
    return dst


def test_the_held_out_fit_brings_wrong_poses_back(tmp_path, monkeypatch):
    """Held-out cameras turned by 1°, the true bunny and albedo scored through them: the pose fit
    moves every camera (at 40 steps: 0.5–0.6° of rotation and about 1 % of its distance sideways,
    which the image cannot tell from a turn) and the PSNR inside the masks rises (17.3 → 24.2 dB at
    40 steps; over 2 dB asked at 20)."""
    dataset = perturbed_test_split(DATA / "blender", tmp_path / "turned", 1.0)
    exp = load_experiment(dataset_experiment(tmp_path, dataset=dataset))
    monkeypatch.setattr(held_out_alignment, "ITERATIONS", 20)
    truth = DATA / "ground_truth.ply"
    result = score_mesh(exp, truth, values={"albedo": [0.7, 0.6, 0.5]}, align=True, spp=64)
    given, aligned = result.mean("psnr_mask"), result.mean("psnr_mask", aligned=True)
    assert aligned > given + 2, (given, aligned)
    assert all(0.1 < rotation < 2.0 for rotation, _ in result.alignment), result.alignment


def test_evaluate_aligns_the_held_out_cameras_of_a_refined_run(refined_run, monkeypatch):
    """A run that refined its cameras is scored with its held-out cameras fitted first (and as
    given, side by side); ``--align off`` scores them as given only."""
    full, _ = refined_run
    monkeypatch.setattr(held_out_alignment, "ITERATIONS", 3)
    report = api.evaluate([str(full.file)])
    last = report.rows[-1]
    assert last["poses"] == "aligned" and set(last["as_given"]) == {"psnr", "psnr_mask", "ssim", "ssim_mask", "iou"}
    assert len(last["alignment_deg"]) == last["views"] and report.rows[0]["poses"] == "as given"
    assert "poses as given" in (full.run_dir / "held_out" / "held_out.md").read_text()
    plain = score_mesh(full, Path(last["mesh"]), values=json.loads((full.run_dir / "optimize.json").read_text())["values"])
    assert plain.mean("psnr") == pytest.approx(last["as_given"]["psnr"]) and not plain.aligned
    # the held-out photographs were taken with the training views' camera: its refined focal length
    s = math.exp(float(np.ravel(State.load(full.run_dir / "state.npz").values["camera_focal"])[0]))
    assert s != 1.0 and last["focal_scales"] == pytest.approx([s] * last["views"], rel=1e-9)
    assert "refined focal length" in (full.run_dir / "held_out" / "held_out.md").read_text()
    test = dataset_scene(full, split="test")
    refocused, _ = refocused_held_out(test, full.run_dir / "cameras.json")
    tan = lambda c: math.tan(math.radians(c.fov) / 2)  # noqa: E731
    assert all(tan(a) / tan(b) == pytest.approx(s, rel=1e-9) for a, b in zip(test.scene.cameras, refocused.scene.cameras))


def test_auto_refines_datasets_only(tmp_path):
    """``auto``: on for a camera dataset with two views or more, off for rendered targets and
    under Mitsuba's engine; ``on`` with one view, or with Mitsuba's engine, is one line."""
    exp = load_experiment(dataset_experiment(tmp_path))
    assert with_camera_mode(exp, 16).optimize.cameras.mode == "on"
    assert with_camera_mode(exp, 1).optimize.cameras.mode == "off"
    mitsuba = replace(exp, estimator=replace(exp.estimator, engine="mitsuba"))
    assert with_camera_mode(mitsuba, 16).optimize.cameras.mode == "off"
    scene_targets = replace(exp, optimize=replace(exp.optimize, target_dataset=None))
    assert with_camera_mode(scene_targets, 16).optimize.cameras.mode == "off"
    on = replace(exp, optimize=replace(exp.optimize, cameras=CamerasUnknown(mode="on")))
    with pytest.raises(PsdrError, match="one view cannot refine its pose"):
        with_camera_mode(on, 1)
    with pytest.raises(PsdrError, match="needs estimator.engine psdr"):
        with_camera_mode(replace(on, estimator=replace(on.estimator, engine="mitsuba")), 16)


@pytest.mark.parametrize("value, message", [
    ("sometimes", r"unknown .sometimes. \(expected auto, on, off\)"),
    ({"rotation": False, "translation": False}, "expected rotation or translation"),
    ({"learning_rate": -1}, "expected a number > 0"),
    ({"start": -3}, "expected an integer >= 0"),
    ({"focus": 1}, "focus"),
])
def test_bad_cameras_keys_are_one_line(tmp_path, value, message):
    path = dataset_experiment(tmp_path, cameras=value)
    with pytest.raises(PsdrError, match=message) as err:
        load_experiment(path)
    assert "optimize.cameras" in str(err.value) and "\n" not in str(err.value)
