"""Several views traced as one wavefront (issue 38): each lane's camera ray is its own view's, and
the batched interior and primary passes and the batched primal render are the per-view
estimators (they differ from a per-view pass no more than two independent per-view passes differ
from each other); a batch of one view is the per-view pass bit for bit."""
from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import psdr_cli
from psdr_cli import backend, estimate, iteration
from psdr_cli.estimate import Settings
from psdr_cli.estimators import registry
from psdr_cli.estimators.boundary_sampling import edge_list
from psdr_cli.estimators.camera import Projection, views_camera_rays
from psdr_cli.estimators.passes import make_sampler
from psdr_cli.estimators.primary import Curves, ViewCurves, draw_curves
from psdr_cli.render import render_view, render_views
from psdr_cli.scene import build_scene

CONFIG = Path(__file__).resolve().parents[1] / "configs" / "reconstruct_bunny.yaml"
VIEWS = [0, 5, 9]


@pytest.fixture(scope="module")
def exp():
    e = psdr_cli.load_experiment(CONFIG)
    e = replace(e, scene=replace(e.scene, width=20, height=14))  # not square: W and H must not swap
    backend.activate(e)
    return e


def test_each_lane_ray_leaves_its_own_camera_through_its_own_pixel(exp):
    scene = build_scene(exp)
    width, height, spp = 20, 14, 3
    sensors = [scene.sensors[v] for v in VIEWS]
    ray, _ = views_camera_rays(sensors, make_sampler(7, width * height * spp * len(VIEWS)), width, height, spp)
    lane = np.arange(width * height * spp * len(VIEWS))
    view, pixel = lane // (width * height * spp), (lane % (width * height * spp)) // spp
    for k, sensor in enumerate(sensors):
        mine = view == k
        proj = Projection(sensor)
        origin = np.ravel(np.asarray(proj.origin))[:3]
        o = np.stack([np.asarray(c) for c in ray.o], 1)[mine]
        d = np.stack([np.asarray(c) for c in ray.d], 1)[mine]
        assert np.linalg.norm(np.cross(o - origin, d), axis=1).max() < 1e-5  # its line passes the camera
        q, _ = proj(mi.Point3f(ray.o + 2.0 * ray.d))  # a point (a vector would not be translated)
        x, y = np.asarray(q.x)[mine], np.asarray(q.y)[mine]
        assert np.all((x > pixel[mine] % width - 1e-3) & (x < pixel[mine] % width + 1 + 1e-3))
        assert np.all((y > pixel[mine] // width - 1e-3) & (y < pixel[mine] // width + 1 + 1e-3))


def vertex_leaf(scene):
    """The bunny's vertex buffer as a fresh AD leaf in the scene."""
    params = mi.traverse(scene.mi_scene)
    V = mi.Float(dr.detach(params["bunny.vertex_positions"]))
    dr.enable_grad(V)
    params["bunny.vertex_positions"] = V
    params.update()
    return V


def term_estimate(scene, exp, term, spp, seed, batched):
    """(images (views, W·H·3), vertex gradient of Σ_v Σ w·I_v) of one pass of ``term`` per view,
    or of one batched pass of all ``VIEWS``."""
    V = vertex_leaf(scene)
    settings = Settings.from_experiment(exp, spp=spp)
    edges = edge_list(scene, exp.estimator, False)
    t = registry.term(term)
    if batched:
        images = t.estimate_views(scene, edges, VIEWS, spp, seed, exp.estimator, settings.max_depth)
    else:
        images = [t.estimate(scene, edges, v, spp, seed + 101 * v, exp.estimator, settings.max_depth)
                  for v in VIEWS]
    w = dr.sin(dr.arange(mi.Float, dr.width(images[0])) * 0.37)  # a fixed weighting of the pixels
    dr.backward(sum(dr.sum(w * img) for img in images))
    return np.stack([np.asarray(dr.detach(i)) for i in images]), np.asarray(dr.grad(V))


def test_batched_interior_pass_is_the_per_view_estimator(exp):
    scene = build_scene(exp)
    a_img, a_grad = term_estimate(scene, exp, "interior", 16, 11, batched=False)
    b_img, b_grad = term_estimate(scene, exp, "interior", 16, 23, batched=False)
    c_img, c_grad = term_estimate(scene, exp, "interior", 16, 37, batched=True)
    noise_img = np.abs(a_img - b_img).mean(axis=1)  # two independent per-view passes, per view
    noise_grad = np.linalg.norm(a_grad - b_grad)
    assert noise_grad > 0 and np.all(noise_img > 0)
    # the batched pass differs from a per-view pass as much as a second per-view pass does
    assert np.all(np.abs(c_img - a_img).mean(axis=1) < 1.5 * noise_img)
    assert np.linalg.norm(c_grad - a_grad) < 1.5 * noise_grad
    # each view's image is its own: two views differ by more than the tolerance above (else a view
    # swapped for another in the batch would pass)
    assert np.abs(c_img[0] - a_img[1]).mean() > 2.0 * noise_img.max()


def test_batched_primary_pass_is_the_per_view_estimator(exp):
    """The primary term's images carry only derivatives: compared through the vertex gradient,
    overall and view by view (each view's own weighting of its pixels)."""
    scene = build_scene(exp)
    grads = {}
    for name, seed, batched in (("a", 11, False), ("b", 23, False), ("c", 37, True)):
        grads[name] = [term_estimate_view(scene, exp, "primary", 256, seed, batched, k) for k in range(len(VIEWS))]
    for k in range(len(VIEWS)):
        a, b, c = grads["a"][k], grads["b"][k], grads["c"][k]
        noise = np.linalg.norm(a - b)
        assert noise > 0
        assert np.linalg.norm(c - a) < 1.5 * noise
        # the views' gradients differ by more than the tolerance (a swapped view would fail)
        assert np.linalg.norm(grads["a"][(k + 1) % len(VIEWS)] - a) > 2.0 * noise


def term_estimate_view(scene, exp, term, spp, seed, batched, k):
    """The vertex gradient of Σ w·I of view ``VIEWS[k]`` alone, from a per-view or a batched pass."""
    V = vertex_leaf(scene)
    settings = Settings.from_experiment(exp, spp=spp)
    settings = settings.with_estimator(primary_spp=spp)
    edges = edge_list(scene, exp.estimator, False)
    t = registry.term(term)
    if batched:
        image = t.estimate_views(scene, edges, VIEWS, spp, seed, exp.estimator, settings.max_depth)[k]
    else:
        image = t.estimate(scene, edges, VIEWS[k], spp, seed, exp.estimator, settings.max_depth)
    w = dr.sin(dr.arange(mi.Float, dr.width(image)) * 0.37)
    dr.backward(dr.sum(w * image))
    return np.asarray(dr.grad(V))


def test_batched_render_is_the_per_view_render(exp):
    scene = build_scene(exp)
    per_view = [np.ravel(render_view(scene, v, 32, seed=s)) for v, s in zip(VIEWS, (1, 2, 3))]
    again = [np.ravel(render_view(scene, v, 32, seed=s)) for v, s in zip(VIEWS, (4, 5, 6))]
    batched = [np.asarray(i) for i in render_views(scene, VIEWS, 32, seed=7)]
    for a, b, c in zip(per_view, again, batched):
        noise = np.abs(a - b).mean()
        assert 0 < np.abs(c - a).mean() < 1.5 * noise
    assert np.abs(batched[0] - per_view[1]).mean() > 2.0 * np.abs(per_view[0] - again[0]).mean()


def test_a_batch_of_one_view_is_the_per_view_pass(exp):
    scene = build_scene(exp)
    settings = Settings.from_experiment(exp)
    vertex_leaf(scene)
    one = estimate.ad_images(scene, None, [5], ["interior"], settings, pass_index=3)[0]
    ref = estimate.ad_image(scene, None, 5, ["interior"], settings, pass_index=3)
    assert np.array_equal(np.asarray(dr.detach(one)), np.asarray(dr.detach(ref)))
    adjoint = iteration.adjoint_images(scene, [5], 4, 0, 3)[0]
    assert np.array_equal(np.asarray(adjoint), np.asarray(iteration.adjoint_image(scene, 5, 4, 0, 3)))


def test_each_lane_draws_a_curve_of_its_own_view_with_its_views_density(exp):
    """``primary.draw_curves``: lanes of view 0 draw among its curves 0–2 ∝ mass, lanes of view 2 among
    its curves (3–4 after view 0's), with 1/(N·p) scaled by their own view's total mass; a view
    without curves (1) draws nothing."""
    n = 4000
    live = {0: ViewCurves(Curves(mi.Point3f(), mi.Point3f(), *[np.zeros(3, np.int64)] * 4, np.ones(3, bool),
                                 np.ones(3, bool)), None, None, None, mi.Float([1.0, 0.0, 3.0]), 4.0),
            2: ViewCurves(Curves(mi.Point3f(), mi.Point3f(), *[np.zeros(2, np.int64)] * 4, np.ones(2, bool),
                                 np.ones(2, bool)), None, None, None, mi.Float([0.0, 2.0]), 2.0)}
    view = dr.arange(mi.UInt32, 3 * n) // n
    u = (mi.Float(dr.arange(mi.UInt32, 3 * n) % n) + 0.5) / n
    k, s, scale, alive = draw_curves(live, u, view, n)
    k, scale, alive, view = np.asarray(k), np.asarray(scale), np.asarray(alive), np.asarray(view)
    assert set(k[view == 0]) == {0, 2} and abs(np.mean(k[view == 0] == 2) - 0.75) < 0.01
    assert set(k[view == 2]) == {4}
    assert np.allclose(scale[view == 0], 4.0 / n) and np.allclose(scale[view == 2], 2.0 / n)
    assert alive[view != 1].all() and not alive[view == 1].any()
