"""Several views traced as one wavefront (issue 38): each lane's camera ray is its own view's, and
the batched interior pass and the batched primal render are the per-view estimators (they differ
from a per-view pass no more than two independent per-view passes differ from each other); a
batch of one view is the per-view pass bit for bit."""
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
from psdr_cli.jitarray import concat
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



def test_joined_arrays_do_not_bake_their_widths_into_kernels(exp):
    """``jitarray.concat`` (curve lists, every iteration of another length) gives ``dr.concat``'s
    values and gradients, and parts of other widths reuse the same kernels."""
    hashes = []
    for widths in ((3, 5), (6, 2)):
        parts = [mi.Point3f(dr.arange(mi.Float, w) * (j + 1), 2.0, dr.arange(mi.Float, w)) for j, w in enumerate(widths)]
        for p in parts:
            dr.enable_grad(p)
        dr.set_flag(dr.JitFlag.KernelHistory, True)
        joined = concat(parts)
        dr.eval(joined)
        history = dr.kernel_history()
        dr.set_flag(dr.JitFlag.KernelHistory, False)
        hashes.append(sorted(k["hash"] for k in history if k["type"] == dr.KernelType.JIT))
        reference = dr.concat([p.x for p in parts])
        assert np.array_equal(np.asarray(joined.x), np.asarray(dr.detach(reference)))
        dr.backward(dr.sum(joined.x * dr.arange(mi.Float, sum(widths))))
        assert np.array_equal(np.asarray(dr.grad(parts[1].x)), np.arange(widths[0], sum(widths)))
    assert hashes[0] == hashes[1]
