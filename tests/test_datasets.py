"""Camera datasets (psdr_cli/datasets): Blender, transforms.json and COLMAP (text and binary)
read into the same frames; image decoding, downsampling, undistortion and every bad input as
one PsdrError line naming the file."""
import json
import os
import shutil
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest
from scipy.spatial.transform import Rotation

from psdr_cli.datasets import Frame, load_views, read_frames, split_views, view_intrinsics
from psdr_cli.datasets import undistort as undistort_module
from psdr_cli.datasets.frames import opencv_matrix, opengl_to_opencv
from psdr_cli.datasets.images import downsample, read_image, read_mask, srgb_to_linear
from psdr_cli.errors import PsdrError, PsdrWarning
from psdr_cli.support.fileio import write_exr

W, H, F = 16, 12, 14.0  # image size and focal length (pixels) of the small datasets
EYES = [(0.0, -4.0, 1.0), (3.0, -3.0, 2.0), (-3.5, -1.0, 0.5), (0.5, 4.0, 1.5)]


def look_at(eye, target=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Camera-to-world in OpenCV axes (x right, y down, z forward) looking from eye to target."""
    eye, target, up = (np.asarray(v, float) for v in (eye, target, up))
    z = (target - eye) / np.linalg.norm(target - eye)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = x, np.cross(z, x), z, eye
    return m


CAMERAS = [look_at(e) for e in EYES]


def write_png(path, pixels):
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), pixels)


def make_image(i, size=(W, H), alpha=False):
    """A small 8-bit BGR(A) image, different per view."""
    w, h = size
    img = np.zeros((h, w, 4 if alpha else 3), np.uint8)
    img[..., 0] = 40 * i
    img[..., 1] = np.arange(w)[None, :] * 10
    img[..., 2] = np.arange(h)[:, None] * 15
    if alpha:
        img[..., 3] = 255
    return img


def write_blender(folder, cameras=CAMERAS, splits=("train", "test"), alpha=True):
    fov = 2 * np.arctan(0.5 * W / F)
    per_split = {s: [] for s in splits}
    for i, c2w in enumerate(cameras):
        split = splits[i % len(splits)] if len(splits) > 1 and i == len(cameras) - 1 else splits[0]
        write_png(folder / split / f"r_{i}.png", make_image(i, alpha=alpha))
        per_split[split].append({"file_path": f"./{split}/r_{i}", "transform_matrix": opengl_to_opencv(c2w).tolist()})
    for split, frames in per_split.items():
        (folder / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": fov, "frames": frames}))
    return folder


def write_transforms(folder, cameras=CAMERAS, extra=None, frame_extra=None, fl=(F, F)):
    frames = []
    for i, c2w in enumerate(cameras):
        write_png(folder / "images" / f"{i:03d}.png", make_image(i))
        frames.append({"file_path": f"images/{i:03d}.png", "transform_matrix": opengl_to_opencv(c2w).tolist(),
                       **((frame_extra or {}).get(i, {}))})
    data = {"fl_x": fl[0], "fl_y": fl[1], "cx": W / 2, "cy": H / 2, "w": W, "h": H, "frames": frames, **(extra or {})}
    (folder / "transforms.json").write_text(json.dumps(data))
    return folder


def colmap_pose_line(image_id, c2w, camera_id, name):
    w2c = np.linalg.inv(c2w)
    qx, qy, qz, qw = Rotation.from_matrix(w2c[:3, :3]).as_quat()
    numbers = " ".join(repr(float(v)) for v in (qw, qx, qy, qz, *w2c[:3, 3]))
    return f"{image_id} {numbers} {camera_id} {name}\n\n"


def write_colmap(folder, cameras=CAMERAS, camera_line=f"1 PINHOLE {W} {H} {F} {F} {W / 2} {H / 2}",
                 ext="png", points=True):
    model = folder / "sparse" / "0"
    model.mkdir(parents=True)
    (model / "cameras.txt").write_text(f"# cameras\n{camera_line}\n")
    lines = "".join(colmap_pose_line(i + 1, c2w, 1, f"{i:03d}.{ext}") for i, c2w in enumerate(cameras))
    (model / "images.txt").write_text("# images\n" + lines)
    if points:
        (model / "points3D.txt").write_text("")
    for i in range(len(cameras)):
        write_png(folder / "images" / f"{i:03d}.{ext}", make_image(i))
    return folder


def binary_copy(text_folder, folder):
    """The same COLMAP dataset with its model written by pycolmap in binary form."""
    shutil.copytree(text_folder / "images", folder / "images")
    (folder / "sparse" / "0").mkdir(parents=True)
    pycolmap.Reconstruction(str(text_folder / "sparse" / "0")).write_binary(str(folder / "sparse" / "0"))
    return folder


def geometry(view):
    return view.fx, view.fy, view.cx, view.cy, view.width, view.height


def expect_error(call, *parts):
    """Run ``call``: a PsdrError of one line that mentions every part."""
    with pytest.raises(PsdrError) as info:
        call()
    message = str(info.value)
    assert "\n" not in message
    for part in parts:
        assert str(part) in message, message
    return message


# --- formats agree ------------------------------------------------------------------------------

def test_every_format_gives_the_same_cameras(tmp_path):
    folders = {
        "blender": write_blender(tmp_path / "blender", splits=("train",)),
        "transforms": write_transforms(tmp_path / "ngp"),
        "colmap": write_colmap(tmp_path / "colmap"),
    }
    folders["colmap_bin"] = binary_copy(folders["colmap"], tmp_path / "colmap_bin")
    assert (folders["colmap_bin"] / "sparse" / "0" / "cameras.bin").is_file()
    for fmt, folder in folders.items():
        frames = read_frames(folder)  # format: auto
        assert [f.split for f in frames] == ["train"] * len(CAMERAS), fmt
        assert len(frames) == len(CAMERAS)
        for frame, c2w in zip(frames, CAMERAS, strict=True):
            assert isinstance(frame, Frame) and frame.distortion == () and frame.mask is None
            np.testing.assert_allclose(frame.cam_to_world, c2w, atol=1e-9, err_msg=fmt)
            np.testing.assert_allclose([frame.fx, frame.fy, frame.cx, frame.cy], [F, F, W / 2, H / 2], atol=1e-9)
            assert (frame.width, frame.height) == (W, H)
    explicit = read_frames({"path": folders["colmap"], "format": "colmap", "model": "sparse/0", "images": "images"},
                           base=folders["colmap"])
    assert [f.name for f in explicit] == ["000.png", "001.png", "002.png", "003.png"]
    assert not any(f.has_alpha for f in explicit)

    class Section:  # a spec given as an object with attributes (an experiment's dataset section)
        path, format, images, masks, key = folders["colmap"], "colmap", None, None, "x.yaml: optimize.dataset"
        downsample = 2  # other attributes are not the reader's business

    assert len(read_frames(Section())) == len(CAMERAS)
    Section.format = "blender"
    expect_error(lambda: read_frames(Section()), "transforms_train.json")
    Section.format = "fbx"
    expect_error(lambda: read_frames(Section()), "x.yaml: optimize.dataset: format", "expected blender")


def test_opengl_to_opencv_puts_the_origin_at_the_principal_point(tmp_path):
    # camera at (0, -4, 0) looking at the origin, world z up; OpenGL axes: x right, y up, z backward
    gl = np.array([[1, 0, 0, 0], [0, 0, -1, -4], [0, 1, 0, 0], [0, 0, 0, 1]], float)
    write_png(tmp_path / "a.png", make_image(0))
    (tmp_path / "transforms_train.json").write_text(json.dumps(
        {"camera_angle_x": 2 * np.arctan(0.5 * W / F),
         "frames": [{"file_path": "a", "transform_matrix": gl.tolist()}]}))
    frame = read_frames({"path": tmp_path, "format": "blender"})[0]
    k = np.array([[frame.fx, 0, frame.cx], [0, frame.fy, frame.cy], [0, 0, 1]])
    w2c = np.linalg.inv(frame.cam_to_world)

    def project(p):
        uvw = k @ w2c[:3] @ np.append(p, 1.0)
        return uvw[:2] / uvw[2]

    np.testing.assert_allclose(project([0, 0, 0]), [W / 2, H / 2], atol=1e-12)
    assert project([0, 0, 0.5])[1] < H / 2  # world up is image up (v grows downwards)
    assert project([0.5, 0, 0])[0] > W / 2  # world +x is image right
    assert (w2c[:3] @ [0, 0, 0, 1])[2] == pytest.approx(4.0)  # in front: z forward


def test_blender_splits_alpha_and_names(tmp_path):
    folder = write_blender(tmp_path / "b", splits=("train", "test"))
    frames = read_frames(folder)
    assert [f.split for f in frames] == ["train", "train", "train", "test"]
    assert [f.name for f in read_frames(folder / "transforms_test.json")] == [f.name for f in frames]
    assert frames[0].name == "train/r_0" and frames[0].image.name == "r_0.png"
    assert all(f.has_alpha for f in frames)
    views = load_views(frames)
    assert views[0].mask is not None and np.all(views[0].mask == 1.0)
    train, held_out = split_views(views)
    assert (len(train), [v.name for v in held_out]) == (3, ["test/r_3"])
    held = split_views(frames, holdout_every=2)  # frames or views
    assert [f.name for f in held.held_out] == ["train/r_0", "train/r_2"] and held.held_out[0].split == "test"
    assert {f.split for f in held.train} == {"train"}
    val = write_blender(tmp_path / "v", splits=("train", "val"))
    assert [f.name for f in split_views(read_frames(val)).held_out] == ["val/r_3"]  # val when there is no test


def test_transforms_intrinsics_distortion_masks_splits_and_applied_transform(tmp_path):
    folder = write_transforms(tmp_path / "t", extra={"camera_model": "OPENCV", "k1": 0.1, "p2": 0.01,
                                                     "val_filenames": ["images/001.png"]},
                              frame_extra={2: {"fl_x": 15.0, "cx": 7.5, "mask_path": "masks/002.png"}})
    write_png(folder / "masks" / "002.png", np.full((H, W), 255, np.uint8))
    frames = read_frames(folder / "transforms.json")
    assert frames[0].distortion == (0.1, 0.0, 0.0, 0.01)
    assert [f.split for f in frames] == ["train", "val", "train", "train"]
    assert (frames[2].fx, frames[2].fy, frames[2].cx, frames[2].mask.name) == (15.0, F, 7.5, "002.png")
    # nerfstudio's applied_transform A is undone: c2w = A⁻¹ · c2w_file
    a = np.array([[1, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0]], float)
    a4 = np.vstack([a, [0, 0, 0, 1]])
    moved = write_transforms(tmp_path / "ns", cameras=[a4 @ c for c in CAMERAS],
                             extra={"applied_transform": a.tolist()})
    for frame, c2w in zip(read_frames(moved), CAMERAS, strict=True):
        np.testing.assert_allclose(frame.cam_to_world, c2w, atol=1e-12)
    # camera_angle_x as the fallback focal length, camera_model absent = pinhole
    data = json.loads((moved / "transforms.json").read_text())
    for key in ("fl_x", "fl_y", "cx", "cy", "w", "h", "applied_transform"):
        del data[key]
    data["camera_angle_x"] = 2 * np.arctan(0.5 * W / F)
    (moved / "transforms.json").write_text(json.dumps(data))
    frame = read_frames(moved)[0]
    np.testing.assert_allclose([frame.fx, frame.fy, frame.cx, frame.cy], [F, F, W / 2, H / 2])


def test_colmap_distortion_models_and_masks(tmp_path):
    folder = write_colmap(tmp_path / "c", camera_line=f"1 OPENCV {W} {H} 14 14.01 8 6 -0.1 0.02 0.001 0.002",
                          ext="jpg", points=False)
    (folder / "masks").mkdir()
    write_png(folder / "masks" / "000.jpg.png", np.full((H, W), 255, np.uint8))  # COLMAP's naming
    for i in (1, 2, 3):
        write_png(folder / "masks" / f"{i:03d}.png", np.full((H, W), 128, np.uint8))  # by stem
    frames = read_frames({"path": folder, "masks": "masks"}, base=folder)
    assert frames[0].distortion == (-0.1, 0.02, 0.001, 0.002) and frames[0].fy == 14.01
    assert [f.mask.name for f in frames] == ["000.jpg.png", "001.png", "002.png", "003.png"]
    views = load_views(frames, cache=tmp_path / "cache")
    assert views[1].mask.mean() == pytest.approx(128 / 255, abs=1e-3)
    assert views[0].fx == views[0].fy
    model = folder / "sparse" / "0" / "cameras.txt"
    for line, dist in ((f"1 SIMPLE_RADIAL {W} {H} 14 8 6 0.05", (0.05, 0, 0, 0)),
                       (f"1 RADIAL {W} {H} 14 8 6 0.05 -0.01", (0.05, -0.01, 0, 0)),
                       (f"1 SIMPLE_PINHOLE {W} {H} 14 8 6", ())):
        model.write_text(line + "\n")
        frame = read_frames(folder)[0]
        assert frame.distortion == dist and (frame.fx, frame.fy, frame.cx, frame.cy) == (14, 14, 8, 6)


# --- decoding and resampling --------------------------------------------------------------------

def test_srgb_decoding_of_8_and_16_bit_png_and_alpha(tmp_path):
    values8 = np.array([0, 10, 128, 255], np.uint8)
    expected = [0.0, 10 / 255 / 12.92, ((128 / 255 + 0.055) / 1.055) ** 2.4, 1.0]
    rgba = np.zeros((1, 4, 4), np.uint8)
    rgba[0, :, :3] = values8[:, None]
    rgba[0, :, 3] = values8
    write_png(tmp_path / "a8.png", rgba)
    rgb, alpha = read_image(tmp_path / "a8.png")
    np.testing.assert_allclose(rgb[0, :, 1], expected, rtol=1e-12)
    np.testing.assert_allclose(alpha[0], values8 / 255)  # alpha is coverage: never sRGB-decoded
    np.testing.assert_allclose(read_image(tmp_path / "a8.png", linear=True)[0][0, :, 1], values8 / 255)
    values16 = np.array([[0, 2570, 32896, 65535]], np.uint16)
    write_png(tmp_path / "g16.png", values16)
    rgb16, alpha16 = read_image(tmp_path / "g16.png")
    assert alpha16 is None and rgb16.shape == (1, 4, 3)
    np.testing.assert_allclose(rgb16[0, :, 0], srgb_to_linear(values16[0] / 65535), rtol=1e-12)
    assert rgb16[0, 2, 0] == pytest.approx(((32896 / 65535 + 0.055) / 1.055) ** 2.4)
    bgr = np.array([[[10, 20, 200]]], np.uint8)  # OpenCV's BGR order becomes RGB
    write_png(tmp_path / "c.png", bgr)
    np.testing.assert_allclose(read_image(tmp_path / "c.png", linear=True)[0][0, 0], [200 / 255, 20 / 255, 10 / 255])
    write_png(tmp_path / "m.png", np.array([[[0, 0, 255], [255, 255, 0]]], np.uint8))  # mask: first (red) channel
    np.testing.assert_allclose(read_mask(tmp_path / "m.png"), [[1.0, 0.0]])
    # EXR: linear, premultiplied colour divided by A
    write_exr(tmp_path / "e.exr", {"R": np.array([[0.25, 0.0]]), "G": np.array([[0.5, 0.0]]),
                                   "B": np.array([[2.0, 0.0]]), "A": np.array([[0.5, 0.0]])})
    rgb_e, alpha_e = read_image(tmp_path / "e.exr")
    np.testing.assert_allclose(rgb_e[0], [[0.5, 1.0, 4.0], [0.0, 0.0, 0.0]])
    np.testing.assert_allclose(alpha_e[0], [0.5, 0.0])


def test_area_downsampling_and_intrinsics(tmp_path):
    a = np.arange(5 * 7, dtype=float).reshape(5, 7)
    out = downsample(a, 2)  # cropped to 4×6, then 2×2 block means
    assert out.shape == (2, 3)
    assert out[0, 0] == pytest.approx(np.mean([0, 1, 7, 8])) and out[1, 2] == pytest.approx(np.mean([18, 19, 25, 26]))
    assert downsample(np.ones((4, 4, 3)), 4).shape == (1, 1, 3)
    frames = read_frames(write_blender(tmp_path / "b", splits=("train",)))
    full, half = load_views(frames[:1])[0], load_views(frames[:1], downsample=2)[0]
    assert (half.width, half.height) == (W // 2, H // 2)
    assert (half.fx, half.fy, half.cx, half.cy) == (F / 2, F / 2, W / 4, H / 4)
    assert view_intrinsics(frames[0], downsample=2) == geometry(half)
    np.testing.assert_allclose(half.image, downsample(full.image, 2), atol=1e-12)
    for bad in (0, 13, 1.5):
        expect_error(lambda bad=bad: load_views(frames, downsample=bad), "downsample", "integer from 1 to 12")


def test_alpha_images_are_resampled_premultiplied(tmp_path):
    img = np.zeros((2, 2, 4), np.uint8)
    img[..., :3] = (0, 0, 255)  # red where transparent ...
    img[0, 0] = (255, 255, 255, 255)  # ... one opaque white pixel
    write_png(tmp_path / "b" / "a.png", img)
    (tmp_path / "b" / "transforms_train.json").write_text(json.dumps(
        {"camera_angle_x": 1.0, "frames": [{"file_path": "a.png", "transform_matrix": np.eye(4).tolist()}]}))
    view = load_views(read_frames(tmp_path / "b"), downsample=2)[0]
    np.testing.assert_allclose(view.image[0, 0], [1, 1, 1])  # no red bleeding in
    assert view.mask[0, 0] == pytest.approx(0.25)


def test_non_square_pixels(tmp_path):
    near = read_frames(write_transforms(tmp_path / "near", fl=(F, F * 1.004)))
    v = load_views(near[:1])[0]
    assert v.fx == v.fy == pytest.approx(F * 1.002) and (v.width, v.height) == (W, H)
    far = read_frames(write_transforms(tmp_path / "far", fl=(F, 1.5 * F)))
    v = load_views(far[:1])[0]
    assert (v.width, v.height) == (W, 8)  # rows shrunk by 2/3: fy 21 → 14
    assert v.fx == v.fy == pytest.approx(F) and v.cy == pytest.approx(4.0) and v.cx == W / 2
    assert view_intrinsics(far[0]) == geometry(v)
    half = load_views(far[:1], downsample=2)[0]
    assert view_intrinsics(far[0], downsample=2) == geometry(half) and half.image.shape == (4, W // 2, 3)


# --- undistortion -------------------------------------------------------------------------------

def pattern(x, y):
    """A smooth image as a function of normalised camera coordinates."""
    return 0.5 + 0.35 * np.sin(7 * x + 1) * np.cos(6 * y)


def test_undistortion_recovers_the_pinhole_image_and_is_cached(tmp_path, monkeypatch):
    w, h, f, dist = 64, 48, 50.0, (-0.25, 0.06, 0.002, -0.001)
    k = opencv_matrix(f, f, 32.0, 24.0)
    jj, ii = np.mgrid[0:h, 0:w]
    pts = np.stack([ii, jj], -1).reshape(-1, 1, 2).astype(np.float64)  # pixel centres, OpenCV origin
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)
    undist = cv2.undistortPoints(pts, k, np.array(dist), None, np.eye(3), np.eye(3), criteria=criteria)
    undist = undist.reshape(h, w, 2)
    rays = np.concatenate([undist.reshape(-1, 2), np.ones((h * w, 1))], axis=1)
    back, _ = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), k, np.array(dist))
    assert np.max(np.abs(back.reshape(-1, 2) - pts.reshape(-1, 2))) < 1e-6  # the exact inverse
    distorted = pattern(undist[..., 0], undist[..., 1])
    folder = tmp_path / "d"
    write_png(folder / "images" / "a.png", np.round(distorted * 65535).astype(np.uint16))
    write_png(folder / "masks" / "a.png", np.where(undist[..., 0] > 0, 255, 0).astype(np.uint8))
    (folder / "transforms.json").write_text(json.dumps({
        "fl_x": f, "fl_y": f, "cx": 32.0, "cy": 24.0, "w": w, "h": h, "camera_model": "OPENCV",
        "k1": dist[0], "k2": dist[1], "p1": dist[2], "p2": dist[3],
        "frames": [{"file_path": "images/a.png", "mask_path": "masks/a.png", "transform_matrix": np.eye(4).tolist()}]}))
    frames = read_frames(folder)
    cache = tmp_path / "cache"
    expect_error(lambda: load_views(frames, linear=True), "transforms.json", "images/a.png", "cache")
    view = load_views(frames, linear=True, cache=cache)[0]
    assert view.fx == view.fy and (view.width, view.height) == (w, h)
    assert view_intrinsics(frames[0]) == geometry(view)
    x = (np.arange(w) + 0.5 - view.cx) / view.fx
    y = (np.arange(h) + 0.5 - view.cy) / view.fy
    truth = pattern(x[None, :], y[:, None])
    centre = (slice(8, h - 8), slice(8, w - 8))
    assert np.max(np.abs(view.image[..., 0][centre] - truth[centre])) < 5e-3
    mask_truth = np.broadcast_to(x[None, :], (h, w))
    assert np.all(view.mask[np.abs(mask_truth) > 0.05] == (mask_truth[np.abs(mask_truth) > 0.05] > 0))
    files = sorted(cache.iterdir())
    assert [p.name.split("-")[0] for p in files] == ["a", "a"] and files[1].name.endswith(".mask.exr")
    stamps = [p.stat().st_mtime_ns for p in files]
    monkeypatch.setattr(undistort_module, "remap", lambda *a: pytest.fail("undistorted again"))
    again = load_views(frames, linear=True, cache=cache)[0]
    np.testing.assert_array_equal(again.image, view.image)
    assert [p.stat().st_mtime_ns for p in sorted(cache.iterdir())] == stamps


# --- bad inputs ---------------------------------------------------------------------------------

def rewrite_json(path, change):
    data = json.loads(path.read_text())
    change(data)
    path.write_text(json.dumps(data))


def skipped(call, count: int, total: int, *parts):
    """Run ``call`` (frames read): one warning line that counts the skipped frames and names the
    first; returns the frames."""
    with pytest.warns(PsdrWarning) as caught:
        frames = call()
    lines = [str(w.message) for w in caught if issubclass(w.category, PsdrWarning)]
    assert len(lines) == 1 and "\n" not in lines[0], lines
    assert f"{count} of {total} frames skipped, their image is missing" in lines[0], lines[0]
    for part in parts:
        assert part in lines[0], lines[0]
    assert len(frames) == total - count
    return frames


def test_frames_whose_image_is_missing_are_skipped_with_one_warning(tmp_path):
    """As instant-ngp and nerfstudio do, in every format: the frames left keep their cameras; a
    dataset with no image left is one line."""
    b = write_blender(tmp_path / "b", splits=("train",))
    total = len(list((b / "train").glob("*.png")))
    (b / "train" / "r_2.png").unlink()
    (b / "train" / "r_3.png").unlink()
    frames = skipped(lambda: read_frames(b), 2, total, "transforms_train.json", "frames[2] (train/r_2)")
    assert "train/r_2" not in [f.name for f in frames]
    t = write_transforms(tmp_path / "t")
    (t / "images" / "001.png").unlink()
    skipped(lambda: read_frames(t), 1, len(json.loads((t / "transforms.json").read_text())["frames"]),
            "frames[1] (images/001.png)")
    c = write_colmap(tmp_path / "c")
    (c / "images" / "002.png").unlink()
    skipped(lambda: read_frames(c), 1, len(list((c / "images").glob("*.png"))) + 1, "images.txt", "image 3 (002.png)")
    for image in (b / "train").glob("*.png"):
        image.unlink()
    expect_error(lambda: read_frames(b), "transforms_train.json", f"none of its {total} frames has its image",
                 "frames[0] (train/r_0)")


def fox_like_transforms(folder: Path, missing=(1, 4), frames: int = 6) -> Path:
    """A capture laid out as instant-ngp's fox example is (our own numbers): one camera block at
    the top level (fl_x, fl_y, cx, cy, w, h, k1, k2, p1, p2, camera_angle_x, aabb_scale), portrait
    1080×1920 JPEGs in ``images/``, a ``sharpness`` per frame, and some listed frames without an
    image (``missing``)."""
    (folder / "images").mkdir(parents=True)
    data = {"camera_angle_x": 1.16, "camera_angle_y": 1.82, "fl_x": 1402.5, "fl_y": 1398.0, "k1": 0.041,
            "k2": -0.037, "p1": 0.0012, "p2": -0.0007, "cx": 541.3, "cy": 957.8, "w": 1080.0, "h": 1920.0,
            "aabb_scale": 4, "frames": []}
    for i in range(frames):
        angle = 2 * np.pi * i / frames
        eye = np.array([2.5 * np.cos(angle), 2.5 * np.sin(angle), 0.4])
        back = eye / np.linalg.norm(eye)  # OpenGL: the camera looks along -z, at the origin
        right = np.cross([0.0, 0.0, 1.0], back)
        right /= np.linalg.norm(right)
        M = np.eye(4)
        M[:3, 0], M[:3, 1], M[:3, 2], M[:3, 3] = right, np.cross(back, right), back, eye
        name = f"images/{i + 1:04d}.jpg"
        data["frames"].append({"file_path": name, "sharpness": 30.0 + i, "transform_matrix": M.tolist()})
        if i not in missing:
            image = np.full((1920, 1080, 3), 40 + 20 * i, np.uint8)
            cv2.imwrite(str(folder / name), image)
    (folder / "transforms.json").write_text(json.dumps(data, indent=1))
    return folder


def test_a_fox_like_capture_loads_without_its_missing_frames(tmp_path):
    """instant-ngp's example layout: the frames with an image load (portrait, the top-level camera
    block with its distortion), the others are skipped with one warning."""
    folder = fox_like_transforms(tmp_path / "fox")
    frames = skipped(lambda: read_frames(folder), 2, 6, "frames[1] (images/0002.jpg)")
    assert [f.name for f in frames] == ["images/0001.jpg", "images/0003.jpg", "images/0004.jpg", "images/0006.jpg"]
    for f in frames:
        assert (f.width, f.height) == (1080, 1920)
        assert (f.fx, f.fy, f.cx, f.cy) == pytest.approx((1402.5, 1398.0, 541.3, 957.8))
        assert f.distortion == pytest.approx((0.041, -0.037, 0.0012, -0.0007))
    fx, fy, cx, cy, width, height = view_intrinsics(frames[0], downsample=4)
    assert width < height and fx == pytest.approx(fy)  # square pixels, portrait, after undistortion


def test_missing_files_and_frames(tmp_path):
    rewrite_json(write_transforms(tmp_path / "t2") / "transforms.json",
                 lambda d: d["frames"][0].update(mask_path="masks/none.png"))
    expect_error(lambda: read_frames(tmp_path / "t2"), "transforms.json", "frames[0].mask_path", "not found")
    rewrite_json(write_transforms(tmp_path / "t3") / "transforms.json",
                 lambda d: d.update(val_filenames=["images/nothing.png"]))
    expect_error(lambda: read_frames(tmp_path / "t3"), "transforms.json", "val_filenames[0]", "no frame")
    b = write_blender(tmp_path / "b", splits=("train",))
    c2 = write_colmap(tmp_path / "c2")
    (c2 / "masks").mkdir()
    expect_error(lambda: read_frames({"path": c2, "masks": c2 / "masks"}), "masks", "000.png", "expected a mask")
    expect_error(lambda: read_frames(tmp_path / "nothing"), "nothing", "not found")
    (tmp_path / "empty").mkdir()
    expect_error(lambda: read_frames(tmp_path / "empty"), "empty", "cannot tell the dataset format")
    expect_error(lambda: read_frames({"path": b, "format": "colmap"}), str(b), "no COLMAP model")
    expect_error(lambda: read_frames({"path": b, "masks": "m"}), "dataset", "masks", "only for format colmap")
    expect_error(lambda: read_frames({"path": b, "frmat": "x"}), "dataset", "frmat", "unknown key")


def test_images_of_different_sizes_and_corrupt_images(tmp_path):
    b = write_blender(tmp_path / "b", splits=("train",))
    write_png(b / "train" / "r_1.png", make_image(1, size=(8, 6), alpha=True))
    expect_error(lambda: read_frames(b), "transforms_train.json", "frame train/r_1", "8×6", f"{W}×{H}")
    c = write_colmap(tmp_path / "c")
    write_png(c / "images" / "001.png", make_image(1, size=(8, 6)))
    expect_error(lambda: read_frames(c), "images.txt", "001.png", "8×6", f"{W}×{H}")
    t = write_transforms(tmp_path / "t")
    (t / "images" / "002.png").write_bytes(b"not an image at all")
    expect_error(lambda: read_frames(t), "transforms.json", "frames[2]", "002.png", "cannot be decoded")
    t2 = write_transforms(tmp_path / "t2")
    good = (t2 / "images" / "002.png").read_bytes()
    (t2 / "images" / "002.png").write_bytes(good[:40])  # a valid header, then nothing
    frames = read_frames(t2)
    expect_error(lambda: load_views(frames), "002.png", "cannot be decoded")


@pytest.mark.parametrize("matrix, why", [
    (np.full((4, 4), np.nan), "NaN"),
    (np.diag([2.0, 2.0, 2.0, 1.0]), "RᵀR"),
    (np.diag([1.0, 1.0, -1.0, 1.0]), "det R"),
    (np.array([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 1, 1]], float), "last row"),
    (np.eye(3), "shape"),
])
def test_bad_camera_matrices(tmp_path, matrix, why):
    t = write_transforms(tmp_path / "t")
    rewrite_json(t / "transforms.json", lambda d: d["frames"][1].update(transform_matrix=matrix.tolist()))
    expect_error(lambda: read_frames(t), "transforms.json", "frames[1].transform_matrix", why)


def test_unsupported_camera_models(tmp_path):
    c = write_colmap(tmp_path / "c", camera_line=f"1 OPENCV_FISHEYE {W} {H} 14 14 8 6 0 0 0 0")
    expect_error(lambda: read_frames(c), "cameras.txt", "camera 1", "OPENCV_FISHEYE", "not supported")
    binary = binary_copy(c, tmp_path / "cb")
    expect_error(lambda: read_frames(binary), "cameras.bin", "camera 1", "OPENCV_FISHEYE")
    for extra, key in (({"camera_model": "OPENCV_FISHEYE"}, "camera_model"),
                       ({"camera_model": "EQUIRECTANGULAR"}, "camera_model"),
                       ({"is_fisheye": True}, "is_fisheye"),
                       ({"k4": 0.01}, "k4")):
        t = write_transforms(tmp_path / key / str(len(os.listdir(tmp_path))), extra=extra)
        expect_error(lambda t=t: read_frames(t), "transforms.json", key, "expected")


def test_mask_size_must_match(tmp_path):
    t = write_transforms(tmp_path / "t", frame_extra={0: {"mask_path": "masks/0.png"}})
    write_png(t / "masks" / "0.png", np.zeros((6, 8), np.uint8))
    frames = read_frames(t)
    expect_error(lambda: load_views(frames), "masks/0.png", "frame images/000.png", "8×6", f"{W}×{H}")


def test_empty_splits(tmp_path):
    b = write_blender(tmp_path / "b", splits=("train",))
    (b / "transforms_val.json").write_text(json.dumps({"camera_angle_x": 0.8, "frames": []}))
    expect_error(lambda: read_frames(b), "transforms_val.json", "frames", "non-empty")
    views = load_views(read_frames(write_transforms(tmp_path / "t")))
    expect_error(lambda: split_views([v for v in views[:1]], holdout_every=2), "transforms.json", "holdout_every")
    expect_error(lambda: split_views([replace(v, split="test") for v in views]),
                 "transforms.json", "split train", "empty")


def test_colmap_without_images(tmp_path):
    c = write_colmap(tmp_path / "c", cameras=[])
    expect_error(lambda: read_frames(c), "images.txt", "no registered images")
    c2 = write_colmap(tmp_path / "c2")
    shutil.rmtree(c2 / "images")
    expect_error(lambda: read_frames(c2), "images", "not a folder")
    c3 = write_colmap(tmp_path / "c3")
    (c3 / "sparse" / "0" / "images.txt").write_text("1 1 0 0 0 0 0 4 one.png\n\n")
    expect_error(lambda: read_frames(c3), "images.txt", "not a readable COLMAP model")


def test_bad_json(tmp_path):
    t = write_transforms(tmp_path / "t")
    (t / "transforms.json").write_text('{"frames": [\n  {"file_path": "a.png",}\n]}')
    expect_error(lambda: read_frames(t), "transforms.json", "line 2", "not valid JSON")
    (t / "transforms.json").write_text("[1, 2]")
    expect_error(lambda: read_frames(t), "transforms.json", "JSON object")
    b = write_blender(tmp_path / "b", splits=("train",))
    rewrite_json(b / "transforms_train.json", lambda d: d.pop("camera_angle_x"))
    expect_error(lambda: read_frames(b), "transforms_train.json", "camera_angle_x", "missing")
    rewrite_json(b / "transforms_train.json", lambda d: d.update(camera_angle_x="wide"))
    expect_error(lambda: read_frames(b), "transforms_train.json", "camera_angle_x", "positive number")
    b2 = write_blender(tmp_path / "b2", splits=("train",))
    rewrite_json(b2 / "transforms_train.json", lambda d: d["frames"][3].pop("transform_matrix"))
    expect_error(lambda: read_frames(b2), "transforms_train.json", "frames[3].transform_matrix", "missing")
    t2 = write_transforms(tmp_path / "t2")
    rewrite_json(t2 / "transforms.json", lambda d: [d.pop(k) for k in ("fl_x", "fl_y")])
    expect_error(lambda: read_frames(t2), "transforms.json", "frames[0]", "focal length")
    rewrite_json(t2 / "transforms.json", lambda d: d.update(fl_x=F, w=W + 1))
    expect_error(lambda: read_frames(t2), "transforms.json", "frames[0]", f"w = {W + 1}")
    rewrite_json(t2 / "transforms.json", lambda d: d.pop("frames"))
    expect_error(lambda: read_frames(t2), "transforms.json", "frames", "non-empty list")


# --- COLMAP models that pycolmap reads without a word (issue 56) --------------------------------

def edit_images_txt(folder: Path, image_id: int, edit) -> Path:
    """``edit(tokens)`` applied to the pose line of image ``image_id`` in the model's images.txt."""
    path = folder / "sparse" / "0" / "images.txt"
    lines = path.read_text().split("\n")
    for i, line in enumerate(lines):
        if line.split()[:1] == [str(image_id)]:
            lines[i] = " ".join(edit(line.split()))
    path.write_text("\n".join(lines))
    return folder


def with_quaternion(scale: float = 1.0, decimals: int | None = None, zero: bool = False):
    def edit(tokens):
        q = [0.0] * 4 if zero else [scale * float(t) for t in tokens[1:5]]
        tokens[1:5] = [repr(v) if decimals is None else f"{v:.{decimals}f}" for v in q]
        return tokens
    return edit


@pytest.mark.parametrize("camera_line, key, value", [
    (f"1 PINHOLE {W} {H} 0 0 {W / 2} {H / 2}", "fx", "0"),
    (f"1 PINHOLE {W} {H} -14 14 {W / 2} {H / 2}", "fx", "-14"),
    (f"1 SIMPLE_PINHOLE {W} {H} 1e-06 {W / 2} {H / 2}", "f", "1e-06"),
], ids=["zero", "negative", "below-a-pixel"])
def test_a_colmap_camera_without_a_focal_length_is_named_by_file_camera_and_parameter(tmp_path, camera_line, key, value):
    c = write_colmap(tmp_path / "c", camera_line=camera_line)
    expect_error(lambda: read_frames(c), "cameras.txt", f"camera 1 {key}", value)


def test_a_camera_pycolmap_refuses_is_named_by_its_file(tmp_path):
    c = write_colmap(tmp_path / "c", camera_line=f"1 PINHOLE {W} {H} 14 14 nan {H / 2}")
    expect_error(lambda: read_frames(c), "cameras.txt", "not a readable COLMAP model")


def test_a_truncated_cameras_bin_is_one_line(tmp_path):
    b = binary_copy(write_colmap(tmp_path / "c"), tmp_path / "b")
    path = b / "sparse" / "0" / "cameras.bin"
    path.write_bytes(path.read_bytes()[: len(path.read_bytes()) // 2])
    expect_error(lambda: read_frames(b), "cameras.bin", "camera 1")


def test_pycolmaps_own_errors_are_one_line_naming_the_model(tmp_path):
    c = edit_images_txt(write_colmap(tmp_path / "c"), 2, lambda t: t[:8] + ["7"] + t[9:])  # no camera 7
    expect_error(lambda: read_frames(c), "images.txt", "not a readable COLMAP model", "7")


def test_a_zero_quaternion_is_refused_and_unnormalised_ones_are_normalised(tmp_path, recwarn):
    c = edit_images_txt(write_colmap(tmp_path / "zero"), 2, with_quaternion(zero=True))
    expect_error(lambda: read_frames(c), "images.txt", "image 2 (001.png) quaternion", "0 0 0 0")
    clean = read_frames(write_colmap(tmp_path / "clean"))
    for name, edit, warned in (("scaled", with_quaternion(scale=2.0), True),
                               ("rounded", with_quaternion(decimals=4), False)):
        folder = write_colmap(tmp_path / name)
        for image_id in range(1, len(CAMERAS) + 1):
            edit_images_txt(folder, image_id, edit)
        recwarn.clear()
        frames = read_frames(folder)
        for a, b in zip(frames, clean):  # 4 decimals: rotations 10⁻⁴ apart
            assert np.allclose(a.cam_to_world[:3, :3], b.cam_to_world[:3, :3], atol=3e-4), name
        messages = [str(w.message) for w in recwarn.list if "quaternion" in str(w.message)]
        assert len(messages) == int(warned), (name, messages)
        if warned:
            assert "images.txt" in messages[0] and "normalised" in messages[0] and "(the farthest: " in messages[0]


def test_an_image_without_its_points_line_and_two_images_of_one_name_are_refused(tmp_path):
    c = write_colmap(tmp_path / "c")
    path = c / "sparse" / "0" / "images.txt"
    lines = path.read_text().split("\n")
    i = next(k for k, line in enumerate(lines) if line.startswith("2 "))
    path.write_text("\n".join(lines[: i + 1] + lines[i + 2:]))  # image 2's (empty) points line removed
    expect_error(lambda: read_frames(c), "images.txt", f"line {i + 1}", "image '2' has no line of 2D points")
    d = edit_images_txt(write_colmap(tmp_path / "d"), 3, lambda t: t[:9] + ["000.png"])
    expect_error(lambda: read_frames(d), "images.txt", "image 3 (000.png)", "image 1")
    # the last image's points line missing at the end of the file: COLMAP drops that image too
    e = write_colmap(tmp_path / "e")
    path = e / "sparse" / "0" / "images.txt"
    path.write_text(path.read_text().rstrip("\n") + "\n")
    expect_error(lambda: read_frames(e), "images.txt", "image '4' has no line of 2D points (the file ends")


@pytest.mark.parametrize("value, hint", [(40, "looks like degrees (0.6981 rad)"), (3.14159, "between 1° and 170°"),
                                         (0.001, "between 1° and 170°")], ids=["degrees", "180-degrees", "tiny"])
def test_a_field_of_view_outside_1_to_170_degrees_is_named_by_file_and_key(tmp_path, value, hint):
    b = write_blender(tmp_path / "b", splits=("train",))
    rewrite_json(b / "transforms_train.json", lambda d: d.update(camera_angle_x=value))
    expect_error(lambda: read_frames(b), "transforms_train.json", "camera_angle_x", hint)
    t = write_transforms(tmp_path / "t", extra={"fl_x": None, "fl_y": None, "camera_angle_x": value})
    expect_error(lambda: read_frames(t), "transforms.json", "camera_angle_x", hint)
    t2 = write_transforms(tmp_path / "t2", frame_extra={2: {"camera_angle_x": value}}, extra={"fl_x": None})
    expect_error(lambda: read_frames(t2), "transforms.json", "frames[2].camera_angle_x", hint)


def test_a_focal_length_below_a_pixel_is_named_by_file_and_key(tmp_path):
    t = write_transforms(tmp_path / "t", fl=(1e-6, 1e-6))
    expect_error(lambda: read_frames(t), "transforms.json", "fl_x", "1e-06", "at least 1 px")
    t2 = write_transforms(tmp_path / "t2", frame_extra={1: {"fl_y": 0.5}})
    expect_error(lambda: read_frames(t2), "transforms.json", "frames[1].fl_y", "at least 1 px")


def test_rounded_matrices_and_a_byte_order_mark_are_read(tmp_path):
    """Matrices written with 4 or 3 decimals (RᵀR up to ~3·10⁻³ from I) are read as the nearest
    rotation, equal to the exact cameras to the rounding; a UTF-8 byte order mark is read; a shear
    beyond a rounded matrix's (1 %) is still refused."""
    exact = read_frames(write_transforms(tmp_path / "exact"))
    for decimals in (4, 3):
        t = write_transforms(tmp_path / f"d{decimals}")
        rewrite_json(t / "transforms.json", lambda d: [f.update(transform_matrix=np.round(
            np.array(f["transform_matrix"]), decimals).tolist()) for f in d["frames"]])
        for a, b in zip(read_frames(t), exact):
            R = a.cam_to_world[:3, :3]
            assert np.allclose(R.T @ R, np.eye(3), atol=1e-12) and np.linalg.det(R) == pytest.approx(1.0)
            assert np.allclose(a.cam_to_world, b.cam_to_world, atol=2 * 10.0 ** -decimals)
    bom = write_transforms(tmp_path / "bom")
    path = bom / "transforms.json"
    path.write_bytes(b"\xef\xbb\xbf" + path.read_bytes())
    assert len(read_frames(bom)) == len(exact)
    sheared = write_transforms(tmp_path / "sheared")
    rewrite_json(sheared / "transforms.json", lambda d: d["frames"][0].update(
        transform_matrix=(np.array(d["frames"][0]["transform_matrix"]) @ np.diag([1.01, 1, 1, 1])).tolist()))
    expect_error(lambda: read_frames(sheared), "frames[0].transform_matrix", "RᵀR differs from I")


@pytest.mark.parametrize("coefficients, what", [
    ("-1.5 0 0 0", "turns back at radius"),  # r − 1.5 r³ peaks at r = 0.47, inside the corners (0.71)
    ("50 0 0 0", "scale the image by"),      # folds nothing, but zooms the photograph 13×
], ids=["folding", "zooming"])
def test_a_lens_model_that_cannot_be_the_lenses_is_refused(tmp_path, coefficients, what):
    c = write_colmap(tmp_path / "c", camera_line=f"1 OPENCV {W} {H} {F} {F} {W / 2} {H / 2} {coefficients}")
    expect_error(lambda: load_views(read_frames(c), cache=tmp_path / "cache"), "images.txt", "000.png", "distortion",
                 what)
    assert not list((tmp_path / "cache").glob("*.exr"))  # refused before anything is written


def test_a_model_in_both_forms_that_disagree_is_read_in_binary_with_a_warning(tmp_path, recwarn):
    text = write_colmap(tmp_path / "c")
    both = binary_copy(text, tmp_path / "both")
    for name in ("cameras.txt", "images.txt", "points3D.txt"):
        shutil.copy(text / "sparse" / "0" / name, both / "sparse" / "0" / name)
    binary = read_frames(both)
    assert not [w for w in recwarn.list if "disagree" in str(w.message)]  # the same model twice: no word
    edit_images_txt(both, 2, lambda t: t[:5] + [repr(float(t[5]) + 0.5)] + t[6:])  # image 2 moved in the text form
    recwarn.clear()
    frames = read_frames(both)
    messages = [str(w.message) for w in recwarn.list if "disagree" in str(w.message)]
    assert len(messages) == 1 and "cameras.bin/images.bin" in messages[0] and "001.png" in messages[0], messages
    assert all(np.array_equal(a.cam_to_world, b.cam_to_world) for a, b in zip(frames, binary))  # COLMAP's choice


def test_a_far_principal_point_is_named_by_file_and_key(tmp_path):
    """A principal point more than an image size from the centre (psdr's cameras cannot hold it)
    named by the camera file and key, not by an image later on."""
    t = write_transforms(tmp_path / "t", extra={"cx": 5000.0})
    expect_error(lambda: read_frames(t), "transforms.json", "cx", "5000", f"from {-W / 2:g} to {1.5 * W:g}")
    t2 = write_transforms(tmp_path / "t2", frame_extra={3: {"cy": -40.0}})
    expect_error(lambda: read_frames(t2), "transforms.json", "frames[3].cy", "-40")
    c = write_colmap(tmp_path / "c", camera_line=f"1 PINHOLE {W} {H} {F} {F} {W / 2} 500")
    expect_error(lambda: read_frames(c), "cameras.txt", "camera 1 cy", "500")
