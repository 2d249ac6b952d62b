"""The coverage image of masked photographs (psdr_cli.estimators.coverage) and its silhouette
derivative, against finite differences of the hit share, per pixel tile and summed."""
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from psdr_cli.estimators.boundary_sampling import edge_list
from psdr_cli.estimators.coverage import coverage_image, hit_share, object_id
from psdr_cli.experiment.load import parse_experiment
from psdr_cli.losses.silhouette import silhouette_loss
from psdr_cli.scene.build import build_scene
from psdr_cli.support import backend

SCENE = {
    "name": "coverage", "seed": 0,
    "scene": {
        "film": {"width": 24, "height": 20}, "max_depth": 2,
        # an off-centre principal point: the silhouettes go through psdr's own film projection
        "cameras": [{"origin": [0.3, -2.4, 0.9], "target": [0, 0, 0.3], "fov": 34, "principal_point": [0.08, -0.05]}],
        "emitters": [{"type": "constant", "radiance": 1.0}],
        "objects": [{"name": "blob", "mesh": {"shape": "bunny", "size": 0.9, "faces": 600},
                     "bsdf": {"type": "diffuse", "reflectance": 0.5}},
                    # a floor behind it everywhere: coverage counts the object's hits, not the floor's
                    {"name": "floor", "mesh": {"shape": "plane", "size": 20}, "edges": False,
                     "transform": {"translate": [0, 0, -0.6]},
                     "bsdf": {"type": "diffuse", "reflectance": 0.5}}]},
    "estimator": {"spp": 16, "primary_spp": 64},
}


def shifted_share(scene, key, V0, shift, spp, seed):
    params = mi.traverse(scene.mi_scene)
    params[key] = mi.Float(np.ravel(V0 + shift).astype(np.float32))
    params.update()
    return np.asarray(hit_share(scene, 0, spp, seed, object_id(scene, "blob")), np.float64)


@pytest.mark.parametrize("axis", [(1.0, 0.0, 0.0), (0.0, 0.0, 1.0)])
def test_coverage_gradient_matches_finite_differences(tmp_path, axis):
    """dC/dθ of a translated bunny (its ears give thin silhouettes) against central differences
    of the hit share at 4096 spp (common random numbers, h = 0.005, 8 repeats); summed over the
    image and over 4×4 tiles, within 4 standard errors of the two estimates (the image sum weighted
    by a ramp across x, so that a sideways motion, which keeps the covered area, shows too). With
    h = 0.01 the differences carried a truncation error: one tile of the z-motion read −5.38
    against −3.72 ± 0.41 at h = 0.005 and −3.50 ± 0.23 / −3.51 ± 0.015 from 48 seeds of the
    estimator with independent / stratified curve draws (z = 11 once the draws were stratified)."""
    exp = parse_experiment(SCENE, Path(tmp_path / "coverage.yaml"))
    backend.activate(exp)
    scene = build_scene(exp)
    edges = edge_list(scene, exp.estimator, False)
    key = "blob.vertex_positions"
    V0 = np.asarray(mi.traverse(scene.mi_scene)[key], np.float64).reshape(-1, 3)
    axis = np.asarray(axis)
    width, height = scene.resolution
    grads = []
    for s in range(12):
        grads.append(np.asarray(_pixel_gradient(scene, edges, key, V0, axis, (100 + s, 200 + s))))
    grads = np.array(grads)
    h = 0.005
    fd = [(shifted_share(scene, key, V0, h * axis, 4096, 7 + r) - shifted_share(scene, key, V0, -h * axis, 4096, 7 + r))
          / (2 * h) for r in range(8)]
    fd = np.array(fd)
    share = shifted_share(scene, key, V0, 0.0 * axis, 256, 3)
    assert 0.05 < share.mean() < 0.6  # the floor fills the rest of the film and does not count
    ramp = np.tile(np.linspace(-1.0, 1.0, width), height) + 0.5  # J = Σ w_p C_p: x-motion shows too
    total, total_fd = grads @ ramp, fd @ ramp
    se = np.hypot(total.std(ddof=1) / np.sqrt(len(total)), total_fd.std(ddof=1) / np.sqrt(len(total_fd)))
    assert abs(total.mean()) > 5 * se, (total.mean(), se)  # a signal to compare
    assert abs(total.mean() - total_fd.mean()) < 4 * se, (total.mean(), total_fd.mean(), se)
    tiles = lambda img: img.reshape(height // 4, 4, width // 4, 4).sum(axis=(1, 3)).ravel()  # noqa: E731
    g_t = np.array([tiles(g.reshape(height, width)) for g in grads])
    f_t = np.array([tiles(f.reshape(height, width)) for f in fd])
    se_t = np.hypot(g_t.std(0, ddof=1) / np.sqrt(len(g_t)), f_t.std(0, ddof=1) / np.sqrt(len(f_t))) + 1e-3
    z = (g_t.mean(0) - f_t.mean(0)) / se_t
    assert np.abs(z).max() < 4.5, np.abs(z).max()
    assert np.corrcoef(g_t.mean(0), f_t.mean(0))[0, 1] > 0.9


def _pixel_gradient(scene, edges, key, V0, axis, seeds):
    """dC_p/dθ of every pixel at θ = 0 (forward mode)."""
    params = mi.traverse(scene.mi_scene)
    t = mi.Float(0.0)
    dr.enable_grad(t)
    V = mi.Point3f(*(mi.Float(V0[:, k]) + t * float(axis[k]) for k in range(3)))
    params[key] = dr.ravel(V)
    params.update()
    est = type("E", (), {"primary_sampling": "length"})()
    C = coverage_image(scene, edges, "blob", 0, seeds, est, spp=4, primary_spp=64)
    dr.forward(t)
    return dr.grad(C)


def test_silhouette_loss_is_the_mean_absolute_difference():
    backend.select_variant("auto")
    C = mi.Float([0.0, 0.5, 1.0, 1.0])
    M = mi.Float([0.0, 1.0, 0.0, 1.0])
    assert float(silhouette_loss(C, M)[0]) == pytest.approx(0.375)
