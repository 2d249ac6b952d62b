"""Several views traced as one wavefront (issue 38): each lane's camera ray is its own view's, and
the batched interior, primary and direct passes and the batched primal render are the per-view estimators
(they differ from a per-view pass no more than two independent per-view passes differ from each
other); a batch of one view is the per-view pass bit for bit."""
from __future__ import annotations

import copy
from dataclasses import replace
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import psdr_cli
from psdr_cli.estimators import registry
from psdr_cli.estimators.boundary_sampling import BoundaryEdges, edge_list
from psdr_cli.estimators.camera import LaneCameras, Projection, camera_ray, views_camera_rays
from psdr_cli.estimators.direct import direct_boundary, views_direct_boundary
from psdr_cli.estimators.indirect import indirect_boundary, views_indirect_boundary
from psdr_cli.estimators.passes import make_sampler
from psdr_cli.estimators.primary import draw_views, view_ranges
from psdr_cli.experiment.load import parse_experiment
from psdr_cli.optimisation import iteration
from psdr_cli.rendering import estimate
from psdr_cli.rendering.estimate import Settings
from psdr_cli.rendering.render import render_view, render_views
from psdr_cli.scene.build import build_scene
from psdr_cli.support import backend
from psdr_cli.support.jitarray import concat
from test_direct_boundary import KEY as SHADOW_KEY, SHADOW

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


def test_lane_rays_are_each_views_mitsuba_camera_rays(exp):
    """``LaneCameras``: lane i's ray is Mitsuba's ``sample_ray`` of its own view's sensor through the
    same film point (origin on the near plane, direction, far end), for views in any order."""
    scene = build_scene(exp)
    width, height = 20, 14
    rng = np.random.default_rng(3)
    order = [VIEWS[2], VIEWS[0], VIEWS[1]]
    view = rng.integers(0, len(order), 2000)
    uv = mi.Point2f(mi.Float(rng.uniform(0, width, 2000)), mi.Float(rng.uniform(0, height, 2000)))
    ray = LaneCameras([scene.sensors[v] for v in order], mi.UInt32(view), width, height)(uv)
    for k, v in enumerate(order):
        reference = camera_ray(scene.sensors[v], uv, width, height)
        mine = view == k
        for a in ("o", "d"):
            ours, theirs = np.asarray(getattr(ray, a))[:, mine], np.asarray(getattr(reference, a))[:, mine]
            assert np.abs(ours - theirs).max() < 1e-5, (v, a)
        assert np.allclose(np.asarray(ray.maxt)[mine], np.asarray(reference.maxt)[mine], rtol=1e-5)


def test_each_lane_draws_a_curve_of_its_own_view_with_its_views_density(exp):
    """``draw_views``: lanes of view 0 draw among its curves 0-3 ∝ mass (never the massless ones),
    lanes of view 2 among its curves (4-5, after view 0's), with 1/(N·p) scaled by their own
    view's total mass; a view without curves (1) draws nothing, and s is uniform on the curve."""
    n = 6000
    masses = [np.array([1.0, 0.0, 3.0, 0.0]), np.zeros(0), np.array([0.0, 2.0])]
    view = dr.arange(mi.UInt32, 3 * n) // n
    u = (mi.Float(dr.arange(mi.UInt32, 3 * n) % n) + 0.5) / n
    start, count = view_ranges([len(m) for m in masses])
    beyond = np.array([5.0, 7.0])  # entries of no view after the last (as padding): never drawn
    draw = draw_views(mi.Float(np.concatenate(masses + [beyond])), start, count, view, u, n)
    k, s, scale, alive = (np.asarray(a) for a in (draw.k, draw.s, draw.scale, draw.alive))
    view = np.asarray(view)
    assert set(k[view == 0]) == {0, 2} and abs(np.mean(k[view == 0] == 2) - 0.75) < 0.01
    assert set(k[view == 2]) == {5}
    assert np.allclose(scale[view == 0], 4.0 / n) and np.allclose(scale[view == 2], 2.0 / n)
    assert alive[view != 1].all() and not alive[view == 1].any()
    assert np.all((s >= 0) & (s < 1)) and abs(s[view == 2].mean() - 0.5) < 0.01


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
    """The primary term's images carry only derivatives: compared through the vertex gradient of
    each view alone (its own weighting of its pixels)."""
    scene = build_scene(exp)
    grads = {name: [term_estimate_view(scene, exp, "primary", 256, seed, batched, k) for k in range(len(VIEWS))]
             for name, seed, batched in (("a", 11, False), ("b", 23, False), ("c", 37, True))}
    a, b, c = (np.stack(grads[name]) for name in "abc")
    noise = np.linalg.norm(a - b, axis=1)  # two independent per-view passes, per view
    assert np.all(noise > 0)
    assert np.all(np.linalg.norm(c - a, axis=1) < 1.5 * noise)
    # the views' gradients differ by more than the tolerance (a view's image handed to another
    # view would fail)
    assert np.linalg.norm(np.roll(a, 1, axis=0) - a) > 2.0 * np.linalg.norm(noise)


def test_batched_direct_pass_is_the_per_view_estimator(tmp_path):
    """The direct term on the shadow scene of test_direct_boundary seen by three cameras: dI/dθ
    (θ = the occluder's x-translation, forward mode) summed over 8 × 8-pixel tiles, per view. The
    mean of two batched passes differs from the mean of four per-view passes by z = |Δ| / (s·√(1/4
    + 1/2)) < 2.5, s the per-view passes' spread (tile noise is heavy-tailed: over four disjoint
    sets of seeds z was 0.53-1.61); the views' tiles differ by far more (14-17 s), and a pass
    whose lanes all land in the first view's image gives z = 10-17 on the views."""
    cfg = copy.deepcopy(SHADOW)
    cfg["scene"]["cameras"] = [{"origin": [0, -2.2, 2.2], "target": [0, 0, 0.2], "fov": 40},
                               {"origin": [1.8, -1.2, 2.4], "target": [0.2, 0.2, 0.0], "fov": 45},
                               {"origin": [-1.5, -1.9, 2.0], "target": [0, 0.3, 0.1], "fov": 38}]
    e = parse_experiment(cfg, tmp_path / "shadow.yaml", cwd=tmp_path)
    backend.activate(e)
    scene = build_scene(e)
    edges = BoundaryEdges.from_scene(scene)
    assert_batched_tiles_match(lambda seed, batched: direct_tiles(scene, edges, seed, batched), views_apart=5.0)


def direct_tiles(scene, edges, seed: int, batched: bool, spp: int = 16) -> np.ndarray:
    """(views, 4·4·3): the direct term's dI/dθ of every view of ``scene`` summed over 8 × 8 tiles
    of its 32 × 32 film, θ the x-translation of the occluder ``occ``."""
    n = spp * 32 * 32

    def trace(P):
        if batched:
            return views_direct_boundary(scene.mi_scene, scene.sensors, edges, P, n, make_sampler(seed, 3 * n),
                                         technique="mis")
        return [direct_boundary(scene.mi_scene, s, edges, P, n, make_sampler(seed + 7 * k, n), technique="mis")
                for k, s in enumerate(scene.sensors)]
    return translation_tiles(scene, SHADOW_KEY, (1, 0, 0), trace)


def translation_tiles(scene, key: str, axis, trace) -> np.ndarray:
    """(views, 4·4·3): dI/dθ of the images ``trace(P)`` returns (one per view, 32 × 32, from the
    AD vertex buffer P of ``key``) summed over 8 × 8 tiles, θ the translation of ``key`` along
    ``axis`` (forward mode)."""
    params = mi.traverse(scene.mi_scene)
    V0 = mi.Float(params[key])
    theta = mi.Float(0.0)
    dr.enable_grad(theta)
    params[key] = dr.ravel(dr.unravel(mi.Point3f, V0) + theta * mi.Vector3f(*axis))
    params.update()
    images = trace(params[key])
    dr.set_grad(theta, 1.0)
    dr.forward_to(*images)
    params[key] = V0
    params.update()
    return np.stack([np.array(dr.grad(i)).reshape(4, 8, 4, 8, 3).sum((1, 3)).ravel() for i in images])


INDIRECT = Path(__file__).resolve().parents[1] / "configs" / "validation" / "indirect.yaml"
INDIRECT_KEY = "ball.vertex_positions"


def test_batched_indirect_pass_is_the_per_view_estimator():
    """The indirect term on the scene lit by way of a wall (configs/validation/indirect.yaml, its
    32 × 32 film) seen by three cameras: dI/dθ (θ = the ball's z-translation) over 8 × 8-pixel
    tiles, per view, as for the direct term above: z < 2.5 for the mean of two batched passes
    against four per-view passes (0.70-1.28 over four disjoint sets of seeds), and the views'
    tiles differ by more than three spreads (5.0-5.4 there), so that a view's image handed to
    another view fails the first test."""
    exp = psdr_cli.load_experiment(INDIRECT)
    cameras = [exp.scene.cameras[0], replace(exp.scene.cameras[0], origin=(-0.8, 1.7, 1.8), target=(-0.4, -0.1, 0.0)),
               replace(exp.scene.cameras[0], origin=(-2.4, 0.3, 0.8), target=(-0.7, -0.5, 0.0))]
    exp = replace(exp, scene=replace(exp.scene, cameras=cameras))
    backend.activate(exp)
    scene = build_scene(exp)
    edges = BoundaryEdges.from_scene(scene)
    assert_batched_tiles_match(lambda seed, batched: indirect_tiles(scene, edges, seed, batched), views_apart=3.0)


def assert_batched_tiles_match(tiles, views_apart: float):
    """``tiles(seed, batched)`` → (views, tiles): the mean of two batched passes differs from the
    mean of four per-view passes by z = |Δ| / (s·√(1/4 + 1/2)) < 2.5 per view, s the per-view
    passes' spread, and the views' mean tiles differ by more than ``views_apart`` spreads."""
    a = np.stack([tiles(seed, False) for seed in (1, 2, 3, 4)])
    c = np.stack([tiles(seed, True) for seed in (11, 12)])
    spread = np.linalg.norm(a.std(axis=0, ddof=1), axis=1)
    assert np.all(spread > 0)
    z = np.linalg.norm(c.mean(axis=0) - a.mean(axis=0), axis=1) / (spread * np.sqrt(1 / 4 + 1 / 2))
    assert np.all(z < 2.5), z
    mean = a.mean(axis=0)
    assert np.linalg.norm(np.roll(mean, 1, axis=0) - mean) > views_apart * np.linalg.norm(spread)


def indirect_tiles(scene, edges, seed: int, batched: bool, spp: int = 256) -> np.ndarray:
    """(views, 4·4·3): the indirect term's dI/dθ of every view of ``scene`` summed over 8 × 8
    tiles of its 32 × 32 film, θ the z-translation of the ball."""
    n, depth = spp * 32 * 32, scene.config.max_depth

    def trace(P):
        if batched:
            return views_indirect_boundary(scene.mi_scene, scene.sensors, edges, P, n, make_sampler(seed, 3 * n), depth)
        return [indirect_boundary(scene.mi_scene, s, edges, P, n, make_sampler(seed + 7 * k, n), depth)
                for k, s in enumerate(scene.sensors)]
    return translation_tiles(scene, INDIRECT_KEY, (0, 0, 1), trace)


def term_estimate_view(scene, exp, term, spp, seed, batched, k):
    """The vertex gradient of Σ w·I of view ``VIEWS[k]`` alone, from a per-view or a batched pass."""
    V = vertex_leaf(scene)
    settings = Settings.from_experiment(exp, spp=spp)
    edges = edge_list(scene, exp.estimator, False)
    t = registry.term(term)
    if batched:
        image = t.estimate_views(scene, edges, VIEWS, spp, seed, exp.estimator, settings.max_depth)[k]
    else:
        image = t.estimate(scene, edges, VIEWS[k], spp, seed + 101 * k, exp.estimator, settings.max_depth)
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
