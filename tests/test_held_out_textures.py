"""``psdr evaluate`` scores a run's held-out views with everything the run recovered: a recovered
albedo texture (and material textures) through the texture coordinates its meshes now carry; and
``--relight`` scores it under other light, against photographs taken under that light.

The capture: a ball whose two halves differ in colour (per-vertex colours read by Mitsuba's
``mesh_attribute`` texture), rendered by Mitsuba's own ``path`` integrator under the studio map
from a ring of cameras, written as a Blender dataset with straight alpha."""
from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import mitsuba as mi
import numpy as np
import pytest
import trimesh
import yaml

from psdr_cli import api
from psdr_cli.commands import evaluate as evaluation
from psdr_cli.errors import PsdrError
from psdr_cli.scoring.held_out import score_mesh
from psdr_cli.experiment.load import load_experiment
from psdr_cli.scene import meshes
from psdr_cli.support import backend, fileio

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE = ROOT / "configs" / "photos" / "bunny_blender.yaml"
SIZE, VIEWS, FOV = 32, 20, 40.0


def two_coloured_ball():
    """(V, F, per-vertex colours): an icosphere of radius 0.5 at the origin, red-orange where
    x > 0 and blue where x < 0 (a smooth step of width 0.1 between)."""
    ball = trimesh.creation.icosphere(subdivisions=3, radius=0.5)
    V, F = np.asarray(ball.vertices), np.asarray(ball.faces)
    t = 1.0 / (1.0 + np.exp(-V[:, 0] / 0.03))
    colours = t[:, None] * [0.8, 0.35, 0.1] + (1 - t[:, None]) * [0.1, 0.25, 0.8]
    return V, F, colours


def opencv_pose(eye) -> np.ndarray:
    """Camera-to-world (OpenCV axes) at ``eye`` looking at the origin, z up."""
    forward = -np.asarray(eye, float) / np.linalg.norm(eye)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    M = np.eye(4)
    M[:3, 0], M[:3, 1], M[:3, 2], M[:3, 3] = right, np.cross(forward, right), forward, eye
    return M


def sun_and_sky(path: Path) -> Path:
    """A 64 × 32 lat-long EXR of our own: a dim blue sky brightening towards the zenith and a small
    warm sun 40° above the horizon (a light unlike the studio map)."""
    H, W = 32, 64
    theta = (np.arange(H) + 0.5) / H * np.pi
    phi = (np.arange(W) + 0.5) / W * 2 * np.pi
    sky = (0.02 + 0.06 * np.cos(theta / 2) ** 2)[:, None, None] * np.array([0.5, 0.7, 1.0])
    texels = np.broadcast_to(sky, (H, W, 3)).copy()
    sun = np.exp(-(((theta[:, None] - np.radians(50)) / 0.12) ** 2 + ((phi[None, :] - 1.0) / 0.12) ** 2))
    texels += 150.0 * sun[..., None] * np.array([1.0, 0.85, 0.6])
    fileio.write_rgb_exr(path, texels)
    return path


def render_capture(folder: Path, envmap: Path = ROOT / "scenes" / "studio.exr", height: float = 0.35) -> Path:
    """The two-coloured ball under ``envmap`` from a ring of VIEWS cameras at about ``height`` ×
    their distance above it (every 5th held out), Blender layout."""
    backend.select_variant("auto")
    V, F, colours = two_coloured_ball()
    mesh = mi.Mesh("ball", len(V), len(F))
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(V.ravel().astype(np.float32))
    params["faces"] = mi.UInt32(F.ravel().astype(np.uint32))
    params.update()
    mesh.add_attribute("vertex_color", 3, mi.Float(colours.ravel().astype(np.float32)))
    mesh.set_bsdf(mi.load_dict({"type": "diffuse", "reflectance": {"type": "mesh_attribute", "name": "vertex_color"}}))
    splits = {"train": [], "test": []}
    for i in range(VIEWS):
        angle = 2 * math.pi * i / VIEWS
        eye = 2.2 * np.array([math.cos(angle), math.sin(angle), height + 0.25 * math.sin(3 * angle)])
        pose = opencv_pose(eye)
        scene = mi.load_dict({
            "type": "scene", "integrator": {"type": "path", "max_depth": 3, "hide_emitters": True},
            "sensor": {"type": "perspective", "fov": FOV, "fov_axis": "x",
                       "to_world": mi.ScalarTransform4f(pose @ np.diag([-1.0, -1.0, 1.0, 1.0])),
                       "film": {"type": "hdrfilm", "width": SIZE, "height": SIZE, "pixel_format": "rgba",
                                "rfilter": {"type": "box"}},
                       "sampler": {"type": "independent", "sample_count": 64}},
            "env": {"type": "envmap", "filename": str(envmap), "scale": 0.8,  # zenith to +z, as psdr turns it
                    "to_world": mi.ScalarTransform4f().rotate([1, 0, 0], 90)},
            "ball": mesh})
        rgba = np.asarray(mi.render(scene, seed=i), np.float64)
        alpha = np.clip(rgba[..., 3:], 0, 1)
        colour = np.where(alpha > 1e-6, rgba[..., :3] / np.maximum(alpha, 1e-6), 0.0)
        srgb = np.where(colour <= 0.0031308, 12.92 * colour, 1.055 * np.clip(colour, 0, 1) ** (1 / 2.4) - 0.055)
        pixels = np.round(255 * np.clip(np.concatenate([srgb, alpha], -1), 0, 1)).astype(np.uint8)
        split = "test" if i % 5 == 0 else "train"
        name = f"{split}/r_{i:03d}"
        (folder / split).mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(folder / f"{name}.png"), cv2.cvtColor(pixels, cv2.COLOR_RGBA2BGRA))
        splits[split].append({"file_path": name, "transform_matrix": (pose @ np.diag([1.0, -1, -1, 1])).tolist()})
    for split, frames in splits.items():
        (folder / f"transforms_{split}.json").write_text(json.dumps(
            {"camera_angle_x": math.radians(FOV), "frames": frames}))
    return folder


@pytest.fixture(scope="module")
def textured_run(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("textured")
    dataset = render_capture(tmp / "ball")
    data = yaml.safe_load(EXAMPLE.read_text())
    data.update(name="ball", output=str(tmp / "runs"))
    data["scene"]["emitters"][0].update(file=str(ROOT / "scenes" / "studio.exr"))
    data["optimize"]["target"]["dataset"] = {"path": str(dataset)}
    data["optimize"].update(iterations=40, batch_size=4, checkpoint_every=20, preview_views=[0], cameras="off",
                            albedo={"texture": [16, 16]}, remesh={"method": "instant", "initial": 600})
    path = tmp / "ball.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    exp = load_experiment(path)
    api.optimize(exp, warn=lambda m: None)
    return exp


def test_the_run_meshes_carry_their_texture_coordinates(textured_run):
    """final.ply and the checkpoints hold the UVs the texture is looked up with."""
    V, F, uv = meshes.read_mesh_file_uv(textured_run.run_dir / "final.ply")
    assert uv is not None and uv.shape == (len(V), 2) and np.isfinite(uv).all()


def test_held_out_scores_use_the_recovered_texture(textured_run):
    """The held-out PSNR of the run with its texture beats the same mesh scored with the
    texture's mean as a constant albedo (the texture matters: the ball's halves differ), and
    ``psdr evaluate`` reports the textured score."""
    exp = textured_run
    values = json.loads((exp.run_dir / "optimize.json").read_text())["values"]
    assert isinstance(values["albedo"], str)
    final = exp.run_dir / "final.ply"
    textured = score_mesh(exp, final, values=values)
    texture = np.asarray(fileio.read_rgb_exr(Path(values["albedo"])), np.float64)
    constant = score_mesh(exp, final, values={"albedo": texture.reshape(-1, 3).mean(0).tolist()})
    assert textured.mean("psnr_mask") > constant.mean("psnr_mask") + 1.0, (textured.mean("psnr_mask"),
                                                                          constant.mean("psnr_mask"))
    report = api.evaluate([str(exp.file)])
    assert report.rows[-1]["psnr_mask"] == pytest.approx(textured.mean("psnr_mask"), abs=1e-6)


@pytest.fixture(scope="module")
def relight_capture(tmp_path_factory):
    """The ball photographed under :func:`sun_and_sky` from another ring of cameras."""
    tmp = tmp_path_factory.mktemp("relight")
    envmap = sun_and_sky(tmp / "sun.exr")
    return render_capture(tmp / "ball_sun", envmap=envmap, height=0.1), envmap


def test_relit_scores_see_the_light(textured_run, relight_capture):
    """Relit by the light the photographs were taken under, the recovered ball scores well above
    the same ball relit by the training light (the per-channel scale cannot turn one light's
    shading into the other's); the map's scale does not change the scores (the per-channel
    least-squares scale absorbs it); relight.json and a strip per view are written."""
    exp = textured_run
    dataset, envmap = relight_capture
    right = api.evaluate([str(exp.file)], relight=api.Relight(dataset, envmap, 0.8)).rows[-1]
    brighter = api.evaluate([str(exp.file)], relight=api.Relight(dataset, envmap, 3.0)).rows[-1]
    wrong = api.evaluate([str(exp.file)], relight=api.Relight(dataset, ROOT / "scenes" / "studio.exr", 0.8)).rows[-1]
    assert right["views"] == VIEWS and right["iou"] > 0.8, right
    assert right["psnr_l"] > wrong["psnr_l"] + 2 and right["ssim"] > wrong["ssim"], (right, wrong)
    for key in ("psnr_h", "psnr_l", "ssim"):
        assert brighter[key] == pytest.approx(right[key], abs=0.05), key
    folder = exp.run_dir / "relight"
    assert json.loads((folder / "relight.json").read_text())["views"] == VIEWS
    assert len(list(folder.glob("*.png"))) == VIEWS


def test_bad_relight_inputs_are_one_line(tmp_path, textured_run, relight_capture, run_psdr):
    """A map that is not a lat-long EXR, a relight dataset in another world frame, --relight
    without --envmap: one line naming the file or option, exit 2."""
    exp = textured_run
    dataset, envmap = relight_capture
    square = tmp_path / "square.exr"
    fileio.write_rgb_exr(square, np.ones((16, 16, 3)))
    moved = tmp_path / "moved"
    moved.mkdir()
    for item in dataset.iterdir():
        if item.suffix == ".json":
            data = json.loads(item.read_text())
            for frame in data["frames"]:
                frame["transform_matrix"] = (np.array(frame["transform_matrix"]) + np.array(
                    [[0, 0, 0, 1.5], [0, 0, 0, 0], [0, 0, 0, 0], [0, 0, 0, 0]])).tolist()
            (moved / item.name).write_text(json.dumps(data))
        else:
            (moved / item.name).symlink_to(item)
    cases = [(("--relight", dataset, "--envmap", square), "not a lat-long map"),
             (("--relight", dataset, "--envmap", tmp_path / "none.exr"), "expected an existing lat-long EXR"),
             (("--relight", moved, "--envmap", envmap), "misses the photographs' masks"),
             (("--relight", dataset), "give both")]
    for args, message in cases:
        r = run_psdr("evaluate", exp.file, *args)
        errors = [line for line in r.stderr.splitlines() if line.startswith("error:")]
        assert r.returncode == 2 and len(errors) == 1 and message in errors[0], (args, r.stderr)
        assert "Traceback" not in r.stderr + r.stdout


def test_held_out_geometry_against_a_reference(tmp_path, textured_run, run_psdr):
    """With ``--reference``: the scale-invariant depth error and the normal angle inside the masks,
    small for the recovered ball against the true one, larger for a squashed ball (and 0 for the
    true ball against itself); a reference in other units (centimetres) is one line."""
    exp = textured_run
    V, F, _ = two_coloured_ball()
    truth = tmp_path / "ball.ply"
    meshes.write_ply(truth, V, F)
    squashed = tmp_path / "squashed.ply"
    meshes.write_ply(squashed, V * [1.0, 1.0, 0.7], F)
    ref = (V, F)
    own = score_mesh(exp, exp.run_dir / "final.ply", reference=ref)
    same = score_mesh(exp, truth, reference=ref)
    flat = score_mesh(exp, squashed, reference=ref)
    assert same.geometry_mean("depth_error") < 1e-9 and same.geometry_mean("normal_deg") < 0.1
    assert own.geometry_mean("depth_error") < 2e-3, own.geometry  # (facets: two tessellations of a ball differ by ~10°)
    assert flat.geometry_mean("normal_deg") > own.geometry_mean("normal_deg") + 2
    assert flat.geometry_mean("depth_error") > own.geometry_mean("depth_error")
    report = api.evaluate([str(exp.file)], reference=truth)
    assert report.rows[-1]["normal_deg"] == pytest.approx(own.geometry_mean("normal_deg"), rel=1e-6)
    centimetres = tmp_path / "cm.ply"
    meshes.write_ply(centimetres, V * 100, F)
    r = run_psdr("evaluate", exp.file, "--reference", centimetres)
    errors = [line for line in r.stderr.splitlines() if line.startswith("error:")]
    assert r.returncode == 2 and len(errors) == 1 and "in other units" in errors[0] and "cm.ply" in errors[0], r.stderr


def test_held_out_views_render_at_the_depth_asked(textured_run, monkeypatch):
    """``psdr evaluate --max-depth 4`` renders the held-out views with paths of 4 segments (the
    scorer gets the experiment at that depth) and says so in its rows and table; without it they
    render at the run's own depth."""
    seen = []
    real = evaluation.score_mesh

    def scoring(exp, mesh, **kwargs):
        seen.append(exp.scene.max_depth)
        return real(exp, mesh, **kwargs)

    monkeypatch.setattr(evaluation, "score_mesh", scoring)
    deep = api.evaluate([str(textured_run.file)], max_depth=4)
    assert seen and set(seen) == {4}
    assert [r["max_depth"] for r in deep.rows] == [4] * len(deep.rows)
    lines = (deep.folders[0] / "held_out.md").read_text().splitlines()
    column = [c.strip() for c in lines[0].split("|")].index("max_depth")
    assert [[c.strip() for c in line.split("|")][column] for line in lines[2:2 + len(deep.rows)]] == ["4"] * len(deep.rows)
    seen.clear()
    own = api.evaluate([str(textured_run.file)])
    assert set(seen) == {textured_run.scene.max_depth} and own.rows[-1]["max_depth"] == textured_run.scene.max_depth


def test_max_depth_is_refused_without_held_out_views(tmp_path, textured_run):
    """``--max-depth`` only means something for a dataset's held-out views: a mesh comparison and
    a relit score refuse it in one line, as does a depth out of range."""
    with pytest.raises(PsdrError, match="--max-depth: only for the held-out views"):
        api.evaluate([str(textured_run.run_dir / "final.ply")], reference=textured_run.run_dir / "final.ply", max_depth=3)
    with pytest.raises(PsdrError, match="--max-depth: not with --relight"):
        api.evaluate([str(textured_run.file)], relight=api.Relight(tmp_path, tmp_path / "sky.exr"), max_depth=3)
    with pytest.raises(PsdrError, match=r"--max-depth: expected an integer in \[1, 64\]"):
        api.evaluate([str(textured_run.file)], max_depth=0)
