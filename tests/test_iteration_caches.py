"""What the optimisation loop computes once and reuses (issue 38) is recomputed as soon as what it
was computed from changes, and reuse gives the result of recomputing."""
from __future__ import annotations

from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

import psdr_cli
from psdr_cli.estimators import primary
from psdr_cli.estimators.boundary_sampling import camera_origins, edge_distribution, edge_list
from psdr_cli.optimisation import iteration
from psdr_cli.optimisation.engines import Engine
from psdr_cli.optimisation.geometry_ahead import GeometryAhead
from psdr_cli.optimisation.problem import Problem, Shape
from psdr_cli.optimisation.stages import stage_of
from psdr_cli.rendering.estimate import Settings
from psdr_cli.scene import meshes
from psdr_cli.scene.build import build_scene
from psdr_cli.support import backend
from psdr_cli.support.jitarray import jit_array

CONFIG = Path(__file__).resolve().parents[1] / "configs" / "reconstruct_bunny.yaml"


def experiment():
    exp = psdr_cli.load_experiment(CONFIG)
    backend.activate(exp)
    return exp


def test_camera_origins_follow_a_moved_sensor():
    scene = build_scene(experiment())
    before = camera_origins(scene.mi_scene)
    assert np.array_equal(camera_origins(scene.mi_scene), before)  # remembered: the same values
    sensor = scene.mi_scene.sensors()[0]
    params = mi.traverse(sensor)
    params["to_world"] = mi.Transform4f().translate([0.1, 0.2, 3.0]) @ params["to_world"]
    params.update()
    after = camera_origins(scene.mi_scene)
    fresh = np.array([np.ravel(s.world_transform().translation()) for s in scene.mi_scene.sensors()])
    assert np.array_equal(after, fresh)
    assert not np.allclose(after[0], before[0]) and np.array_equal(after[1:], before[1:])


def test_edge_memo_is_recomputed_for_a_new_vertex_buffer():
    exp = experiment()
    V, F = meshes.sphere(0.4, 2)
    problem = Problem(exp, Shape(V + [0, 0, 0.42], F), None, {})
    problem.apply()
    problem.scene.objects["bunny"].vertices, problem.scene.objects["bunny"].faces = problem.vertices(), F
    edges = edge_list(problem.scene, exp.estimator, False)
    P = edges.positions(mi.traverse(problem.scene.mi_scene))
    d1 = edge_distribution(edges, P)
    assert edge_distribution(edges, edges.positions(mi.traverse(problem.scene.mi_scene))) is d1  # same buffer
    Q = P * 1.5  # a moved shape: a new buffer, a new distribution, as if built afresh
    d2 = edge_distribution(edges, Q)
    assert d2 is not d1
    assert np.allclose(np.asarray(d2.cdf), np.asarray(edge_distribution(edge_list(problem.scene, exp.estimator, False),
                                                                           Q).cdf))
    assert np.isclose(float(d2.sum()[0]), 1.5 * float(d1.sum()[0]), rtol=1e-5)
    problem.release()


def test_apply_after_a_backward_pass_rebuilds_the_ad_graph():
    """The loop applies twice per iteration (after the step, and when the next one starts): the
    second is skipped, unless a backward pass used up the graph (a skipped update keeps u)."""
    exp = experiment()
    V, F = meshes.sphere(0.4, 2)
    problem = Problem(exp, Shape(V + [0, 0, 0.42], F), None, {})
    grads = []
    for _ in range(2):  # no step in between: u is unchanged, as after a skipped update
        problem.apply()
        problem.apply()  # a no-op
        dr.backward(dr.sum(problem.params[problem.key]))
        problem.invalidate()  # as iterate() does after its backward pass
        grads.append(np.asarray(dr.grad(problem.opt["u"])).copy())
        dr.set_grad(problem.opt["u"], 0.0)
    assert np.abs(grads[0]).sum() > 0
    assert np.array_equal(grads[0], grads[1])
    problem.release()


def test_geometry_computed_ahead_is_the_iterations_own(monkeypatch):
    """The loop builds the edge table and runs the intersection search on a worker thread while the
    adjoint render's kernels run (geometry_ahead.py): the table is edge_list's, column for column
    (with edge sorting: chains and flips), and the primary term finds the search under its digest
    and does not run it again; its curves are those of a search of its own."""
    exp = experiment()
    a, F = meshes.sphere(0.25, 2)
    V = np.concatenate([a + [0, 0, 0.3], a + [0.2, 0, 0.5]])  # one mesh crossing itself
    F = np.concatenate([F, F + len(a)])
    problem = Problem(exp, Shape(V, F), None, {})
    problem.apply()
    problem.scene.objects["bunny"].vertices, problem.scene.objects["bunny"].faces = problem.vertices(), F
    started = GeometryAhead(problem.scene, exp.estimator, True, True)
    ahead = started.edges()
    own = edge_list(problem.scene, exp.estimator, True)
    assert ahead.count == own.count > 0 and ahead.names == own.names
    for x, y in zip(ahead.ids + [ahead.open, ahead.flip], own.ids + [own.open, own.flip]):
        assert np.array_equal(np.asarray(x), np.asarray(y))
    assert np.array_equal(ahead.chains.order, own.chains.order) and np.asarray(own.flip).any()
    scene = problem.scene.mi_scene
    P = ahead.positions(mi.traverse(scene))
    reference = primary.intersection_curves(scene, own, P)  # a search of its own
    assert len(reference) > 20

    def searched_again(*args):
        raise AssertionError("the intersection search ran again")
    monkeypatch.setattr(primary, "intersection_segments", searched_again)
    curves = primary.intersection_curves(scene, ahead, P)
    assert np.array_equal(np.asarray(curves.p0), np.asarray(reference.p0))
    assert np.array_equal(curves.face0, reference.face0) and np.array_equal(curves.face1, reference.face1)
    assert primary.scene_meshes(scene, ahead, P)[0][0][1] is started.arrays[0][0]  # buffers not read again
    problem.release()


def test_an_iteration_searches_intersections_on_the_worker_only(monkeypatch):
    """One loop iteration on a mesh that crosses itself: the primary term's intersection search
    is the worker's (a search on the main thread would call primary.intersection_segments, made
    to fail here; the worker calls the intersections module's own), and the step is finite."""
    exp = experiment()
    a, F = meshes.sphere(0.25, 2)
    V = np.concatenate([a + [0, 0, 0.3], a + [0.2, 0, 0.5]])
    F = np.concatenate([F, F + len(a)])
    problem = Problem(exp, Shape(V, F), None, {})
    engine = Engine(Settings.from_experiment(exp, loop=True))
    W, H = exp.scene.width, exp.scene.height
    targets = [np.full((H, W, 3), 0.2, np.float32) for _ in exp.scene.cameras]
    stage = stage_of(problem, targets, engine.settings, engine.terms)
    loop = iteration.Loop(exp.optimize, engine, 10, print)

    def searched_again(*args):
        raise AssertionError("the intersection search ran on the main thread")
    monkeypatch.setattr(primary, "intersection_segments", searched_again)
    with backend.optimization_threads():
        step = iteration.iterate(problem, loop, stage, iteration.GuideCache(), 0)
    assert np.isfinite(step.loss) and not step.skipped
    problem.release()


def test_leaves_after_an_apply_carry_the_gradient_of_a_fresh_apply():
    """The loop applies after each step in the form its iteration used (problem.write_as_leaves); the
    next iteration's leaves (frozen_batch.py) are then the ones written, with no second scene
    update, and the gradient they carry back to u is that of leaves written afresh."""
    exp = experiment()
    V, F = meshes.sphere(0.4, 2)
    problem = Problem(exp, Shape(V + [0, 0, 0.42], F), None, {})
    weights = mi.Float(np.linspace(-1.0, 2.0, 3 * len(V)))
    updates = []
    update = problem.params.update
    problem.params.update = lambda *a, **k: updates.append(1) or update(*a, **k)
    grads = []
    for reuse in (True, False):
        problem.write_as_leaves(reuse)
        if reuse:
            problem.apply()  # after the step: leaves already
        before = len(updates)
        values, leaves = problem.apply_leaves()
        assert len(updates) == before + (0 if reuse else 1)
        assert problem.params[problem.key].index == leaves[problem.key].index  # the scene's buffer is the leaf
        dr.backward(dr.sum(problem.params[problem.key] * weights))
        problem.backward_leaves(values, leaves)
        problem.invalidate()  # as iterate() does after its backward pass
        grads.append(np.asarray(dr.grad(problem.opt["u"])).copy())
        dr.set_grad(problem.opt["u"], 0.0)
    assert np.abs(grads[0]).sum() > 0
    assert np.allclose(grads[0], grads[1], rtol=1e-6, atol=1e-9)
    problem.apply(leaves=False)  # and back to attached values: a gradient reaches u directly
    dr.backward(dr.sum(problem.params[problem.key] * weights))
    assert np.allclose(np.asarray(dr.grad(problem.opt["u"])), grads[0], rtol=1e-6, atol=1e-9)
    problem.release()


def test_the_edge_draw_compiles_once_for_every_edge_count():
    """The edges' length distribution takes the count as an opaque array: drawing from tables of
    other lengths runs the very kernels of the first (a count written into the kernels as a
    constant compiled them anew every iteration: 4.5 s per iteration of the demo, measured). The
    inputs come from 64-byte aligned memory as the loop's do (:func:`psdr_cli.support.jitarray.jit_array`):
    Dr.Jit writes a mapped numpy array's alignment into the kernel, and arrays mapped straight from
    numpy made the kernels depend on where numpy's allocator put them (this test failed 1 run in 4)."""
    from psdr_cli.estimators.boundary_sampling import BoundaryEdges, length_distribution
    experiment()
    rng = np.random.default_rng(0)
    P = jit_array(mi.Float, rng.uniform(-1, 1, 300))
    u = jit_array(mi.Float, rng.uniform(0, 1, 1000))
    hashes, loaded = [], []
    dr.eval()  # nothing of an earlier test's left to join these kernels
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        for count in (2046, 2049, 2071, 9000):  # (the demo's tables hold about 2000 edges)
            ids = [jit_array(mi.UInt32, rng.integers(0, 100, count)) for _ in range(6)]
            edges = BoundaryEdges(["x"], ids, jit_array(mi.Bool, np.zeros(count, bool)), count)
            dr.kernel_history()  # cleared
            k, s = length_distribution(edges, P).sample_reuse(u)
            dr.eval(k, s)
            history = [h for h in dr.kernel_history() if h["type"] == dr.KernelType.JIT]
            hashes.append(sorted(h["hash"] for h in history))
            # kernels not found in memory (compiled, or loaded from the disk cache)
            loaded.append(sum(1 for h in history if not h.get("cache_hit") or h.get("cache_disk")))
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    assert all(h == hashes[0] for h in hashes[1:]), hashes  # the same kernels, whatever the count
    assert loaded[1:] == [0, 0, 0], loaded


def test_the_length_distribution_draws_as_mitsubas():
    """LengthDistribution against mi.DiscreteDistribution.sample_reuse on lengths with zero-length
    edges (inside and at the end), u at 0, near 1 and in between, and a single edge: the same
    edge for (almost) every u and the same remainder on it."""
    from psdr_cli.estimators.boundary_sampling import LengthDistribution
    experiment()
    rng = np.random.default_rng(3)
    for lengths in (rng.uniform(0.0, 1.0, 500), np.r_[0.0, rng.uniform(0.1, 1.0, 40), 0.0, 0.0], np.array([0.7])):
        lengths = lengths.astype(np.float32)
        lengths[::9] = 0.0 if len(lengths) > 1 else lengths[::9]
        u = mi.Float(np.r_[0.0, 1.0 - 2.0 ** -24, rng.uniform(0.0, 1.0, 20000)].astype(np.float32))
        ours = LengthDistribution(mi.Float(lengths), dr.opaque(mi.UInt32, len(lengths)))
        theirs = mi.DiscreteDistribution(mi.Float(lengths))
        (k1, s1), (k2, s2) = ours.sample_reuse(u), theirs.sample_reuse(u)
        k1, k2, s1, s2 = (np.asarray(x) for x in (k1, k2, s1, s2))
        assert np.isclose(float(ours.sum()[0]), float(theirs.sum()[0]), rtol=1e-6)
        assert (lengths[k1] > 0).all()
        same = k1 == k2
        assert same.mean() > 0.999 and np.abs(s1 - s2)[same].max() < 0.02
