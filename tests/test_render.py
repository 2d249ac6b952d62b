"""Forward rendering: determinism, agreement with Mitsuba's ``path`` integrator, CLI outputs."""
import mitsuba as mi
import numpy as np
import pytest

from psdr_cli.api import setup
from psdr_cli.config.options import parse_views
from psdr_cli.errors import PsdrError
from psdr_cli.experiment.load import parse_experiment
from psdr_cli.rendering.render import passes_for, render_view
from psdr_cli.scene.build import build_scene
from psdr_cli.support import fileio as io

from conftest import experiment, run_cli


def scene_of(d, tmp_path):
    exp = parse_experiment(d, tmp_path / "exp.yaml", cwd=tmp_path)
    setup(exp)
    return build_scene(exp)


def test_same_seed_same_image_other_seed_other_image(tmp_path):
    scene = scene_of(experiment(), tmp_path)
    a = render_view(scene, 0, spp=8, seed=3)
    b = render_view(scene, 0, spp=8, seed=3)
    c = render_view(scene, 0, spp=8, seed=4)
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c) and a.mean() > 0


def test_passes_split_samples_exactly():
    assert passes_for(10, 100, max_lanes=300) == [3, 3, 2, 2]
    assert sum(passes_for(1000, 4096, max_lanes=1 << 16)) == 1000
    assert passes_for(4, 10) == [4]


def block_means(img, b=4):
    H, W, _ = img.shape
    return img[: H // b * b, : W // b * b].reshape(H // b, b, W // b, b, 3).mean(axis=(1, 3))


def compare_with_mitsuba(scene, seeds=6, spp=64):
    """z-scores of our and Mitsuba's per-block means (4×4 pixels, per channel), SE from seed spread."""
    ours = np.stack([block_means(render_view(scene, 0, spp=spp, seed=100 + s)) for s in range(seeds)])
    ref = np.stack([block_means(np.array(mi.render(scene.mi_scene, sensor=0, spp=spp, seed=200 + s)))
                    for s in range(seeds)])
    se = np.sqrt(ours.var(0, ddof=1) / seeds + ref.var(0, ddof=1) / seeds)
    diff = ours.mean(0) - ref.mean(0)
    signal = ref.mean(0) > 1e-3 * ref.mean()
    z = diff[signal] / np.maximum(se[signal], 1e-6 * ref.mean())
    total_z = (ours.mean(axis=(1, 2, 3)).mean() - ref.mean(axis=(1, 2, 3)).mean()) / np.sqrt(
        ours.mean(axis=(1, 2, 3)).var(ddof=1) / seeds + ref.mean(axis=(1, 2, 3)).var(ddof=1) / seeds)
    return z, total_z, ours.mean(), ref.mean()


def envmap_file(tmp_path):
    h, w = 32, 64
    y = np.linspace(1, 0, h)[:, None, None] * np.ones((1, w, 3))
    img = (0.3 + 0.7 * y) * np.array([0.6, 0.7, 1.0])
    img[4:8, 10:16] = 20.0  # a small bright window: a hard case for MIS
    io.write_rgb_exr(tmp_path / "env.exr", img.astype(np.float32))
    return "env.exr"


SCENES = {
    "area_diffuse_direct": lambda tmp: experiment(),
    "envmap_roughconductor_depth3": lambda tmp: {
        **experiment(), "scene": {**experiment()["scene"], "max_depth": 3,
                                  "emitters": [{"type": "envmap", "file": envmap_file(tmp), "rotate_deg": 30}],
                                  "objects": [{**experiment()["scene"]["objects"][0],
                                               "bsdf": {"type": "roughconductor", "alpha": 0.2}},
                                              experiment()["scene"]["objects"][1]]}},
    "sky_principled_plus_area": lambda tmp: {
        **experiment(), "scene": {**experiment()["scene"],
                                  "emitters": [experiment()["scene"]["emitters"][0],
                                               {"type": "sky", "sun_direction": [1, -1, 1.5], "sun_scale": 0.05}],
                                  "objects": [{**experiment()["scene"]["objects"][0],
                                               "bsdf": {"type": "principled", "roughness": 0.4, "metallic": 0.3}},
                                              experiment()["scene"]["objects"][1]]}},
    "constant_roughglass_depth4": lambda tmp: {
        **experiment(), "scene": {**experiment()["scene"], "max_depth": 4,
                                  "emitters": [{"type": "constant", "radiance": [0.8, 0.9, 1.0]}],
                                  "objects": [{**experiment()["scene"]["objects"][0],
                                               "bsdf": {"type": "roughdielectric", "alpha": 0.15}},
                                              experiment()["scene"]["objects"][1]]}},
}


@pytest.mark.parametrize("name", SCENES)
def test_render_agrees_with_mitsuba_path_integrator(tmp_path, name):
    scene = scene_of(SCENES[name](tmp_path), tmp_path)
    z, total_z, ours, ref = compare_with_mitsuba(scene)
    assert ref > 0.01
    assert abs(total_z) < 4, (total_z, ours, ref)
    assert np.abs(z).max() < 5, np.abs(z).max()
    assert np.mean(z ** 2) < 2.0, np.mean(z ** 2)  # ≈ 1 when both estimate the same image


def test_depth_changes_the_image(tmp_path):
    """Sanity check that the comparison above can fail: one bounce more is a different image."""
    d2 = SCENES["constant_roughglass_depth4"](tmp_path)
    d2["scene"]["max_depth"] = 2
    a = render_view(scene_of(d2, tmp_path), 0, spp=64, seed=0)
    d4 = SCENES["constant_roughglass_depth4"](tmp_path)
    ref = np.array(mi.render(scene_of(d4, tmp_path).mi_scene, spp=256, seed=1))
    assert abs(block_means(a).mean() - block_means(ref).mean()) > 0.02 * ref.mean()


def test_cli_render_writes_exr_png_and_summary(tmp_path, write_cfg, run_psdr):
    """`psdr render` (a real process, then --out in this process) writes EXR, PNG and its line."""
    cfg = write_cfg(experiment())
    proc = run_cli("render", cfg, "--spp", "4", "--views", "0", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    folder = tmp_path / "out" / "t" / "render"
    exr = io.read_exr(folder / "view_000.exr")
    assert exr["R"].shape == (16, 24) and exr["G"].mean() > 0
    assert exr["__header__"]["psdr.spp"] == "4"
    assert (folder / "view_000.png").stat().st_size > 100
    assert not list(folder.glob(".*tmp*")), "temporary files left behind"
    assert "psdr render: t" in proc.stdout and "24×16" in proc.stdout

    proc = run_psdr("render", cfg, "--spp", "2", "--out", tmp_path / "elsewhere", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert (tmp_path / "elsewhere" / "t" / "render" / "view_000.exr").exists()


@pytest.mark.parametrize("views", ["0-9999999999", "5-9999999999", "99999999999"])
def test_a_huge_view_range_is_one_line_before_any_list_is_built(views):
    """A range is checked against the view count before its indices are listed (the list of
    10^10 indices ended in an internal MemoryError)."""
    with pytest.raises(PsdrError, match=r"--views: view \d+ does not exist \(the experiment has views 0..5\)"):
        parse_views(views, 6)
