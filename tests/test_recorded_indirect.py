"""The indirect term's recorded part (issue 58, psdr_cli/estimators/recorded_indirect.py) on two
spheres under the sun at max_depth 3, where light between the spheres makes the indirect term
nonzero: a replay gives the term's traced pass for batches, seeds and edge tables it was not
recorded on; a new scene (a remesh) is recorded again and still gives it; and the loop's
iteration with it is the traced iteration, with the indirect term's share resolved."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from psdr_cli.estimators.boundary_sampling import edge_list
from psdr_cli.optimisation import iteration
from psdr_cli.optimisation.engines import Engine
from psdr_cli.optimisation.frozen_batch import FrozenBatch
from psdr_cli.optimisation.problem import adam_export
from psdr_cli.support import backend
from test_frozen_batch import perturbed_shapes, setup, vertex_leaf_written

#: The scene of every test here: two spheres, one in the other's shadow, paths of 3 segments.
SCENE = {"shadowed": True, "max_depth": 3, "width": 32}
INDIRECT = "indirect"


def part_gradients(problem, engine, fbs, edges, views, it, delta) -> list:
    """The vertex leaf's gradient of Σ δ·I_indirect over the batch ``views`` of iteration ``it``,
    from each of ``fbs``: a FrozenBatch's indirect part, or None for the term's traced pass
    (``estimate_views``, the loop's traced path); the vertices written as the loop writes them."""
    V = np.asarray(problem.vertices())
    grads = []
    for fb in fbs:
        leaf = vertex_leaf_written(problem, V)
        if fb is None:
            images = Engine(engine.settings).images(problem, edges, views, it, terms=(INDIRECT,))
            dr.backward(dr.sum(delta * dr.concat(images)))
        else:
            assert fb.serves(INDIRECT, problem, views, engine.settings, edges, None)
            assert fb.record(INDIRECT, problem, views, it, engine.settings, edges=edges, delta=delta) == edges.count
        grads.append(np.asarray(dr.grad(leaf), np.float64))
    return grads


def assert_same_gradient(recorded, traced):
    """Recorded and traced gradients agree to rounding. On LLVM with the loop's one thread the two
    run the same float32 operations in the same order (the camera table's rows are the ones the
    traced pass builds from the same sensors, the samples come from one seed, and the padded edges
    only append zero lengths to the length distribution's prefix sums), so they are equal bit for
    bit (measured: 0). On CUDA the vertex gradients are sums of atomic adds in a scheduling order:
    a sum of n float32 terms reordered changes by about √n·2⁻²⁴ of its terms' magnitude, n ≤ 4096
    lanes here, i.e. ≲ 4·10⁻⁶; the bound is 10⁻⁵ of the largest entry."""
    assert np.abs(traced).sum() > 0
    if mi.variant().startswith("cuda"):
        assert np.abs(recorded - traced).max() <= 1e-5 * np.abs(traced).max()
    else:
        assert np.array_equal(recorded, traced), np.abs(recorded - traced).max()


def test_the_indirect_part_replays_the_traced_term_for_new_batches_and_edge_tables():
    """Four batches (other views, seeds and jittered vertices, so other edge counts) on one scene:
    each replay of the recorded part gives the gradient of the term's traced pass and of the same
    part traced (a stale replay would give the first batch's), with one recording for all of them;
    then a remesh (a new scene, about 4× the edges: more slots) is recorded again and gives the
    traced gradient too. A guided pass is left to the traced term."""
    counts, norms = [], []
    for problem, engine, frozen, traced, trial, _, edges, views, delta in perturbed_shapes(5, **SCENE):
        recorded, part, term = part_gradients(problem, engine, (frozen, traced, None), edges, views, trial, delta)
        assert_same_gradient(recorded, term)
        assert_same_gradient(part, term)
        assert not frozen.serves(INDIRECT, problem, views, engine.settings, edges, {INDIRECT: object()})  # guided
        counts.append(edges.count)
        norms.append(np.abs(term).sum())
    assert len(set(counts)) > 1 and len(set(norms)) == len(norms), (counts, norms)
    assert frozen.parts[INDIRECT].n_recordings == 1  # replayed for every later batch and edge count
    slots = frozen.parts[INDIRECT].slots
    exp, problem, engine, stage = setup(subdivisions=3, **SCENE)  # a remesh builds a new scene
    with backend.optimization_threads():
        frozen.prepare(problem, stage)
        edges = edge_list(problem.scene, engine.settings.estimator, False)
        views = iteration.batch_views(0, 9, len(stage.arrays), exp.optimize.batch_size)
        recorded, term = part_gradients(problem, engine, (frozen, None), edges, views, 9, delta)
    assert_same_gradient(recorded, term)
    assert edges.count > max(counts) and frozen.parts[INDIRECT].slots > slots
    assert frozen.parts[INDIRECT].n_recordings == 2
    problem.release()


def first_moment(frozen: bool, it: int, drop: str | None = None) -> tuple:
    """(loss, Adam's first moment of the vertex latent after one loop iteration ``it`` = (1 − β₁)·g,
    the recordings of each part) on a fresh :data:`SCENE`: with the recorded parts (``frozen``), or
    the traced iteration (Mitsuba's sensor objects, no leaves); ``drop``: a term left out."""
    exp, problem, engine, stage = setup(**SCENE)
    engine.terms = tuple(t for t in engine.terms if t != drop)
    loop = iteration.Loop(exp.optimize, engine, 10, print, frozen=FrozenBatch() if frozen else None)
    with backend.optimization_threads():
        step = iteration.iterate(problem, loop, stage, iteration.GuideCache(), it)
    recordings = {}
    if frozen:
        recordings = {name: part.n_recordings for name, part in loop.frozen.parts.items()}
        recordings["interior"] = loop.frozen.interior.n_recordings
    m = np.asarray(adam_export(problem.opt, "u")[1], np.float64)
    problem.release()
    return step.loss, m, recordings


def test_the_frozen_iteration_at_depth_3_is_the_traced_iteration():
    """One loop iteration at max_depth 3 (all four terms, the interior's depth-3 paths and the
    indirect term recorded: every part records once) against the traced iteration. They differ by
    the rounding of the camera rays (the table's against Mitsuba's sensor objects, as at depth 2:
    test_frozen_batch.py::test_the_frozen_iteration_is_the_traced_iteration), measured 4.5·10⁻⁷ of
    the gradient's L1 at 16 lanes. The indirect term is 0.74 % of that L1 here (the traced
    iteration without it), so the whole-gradient bound of depth 2 (10⁻⁴) would pass a recorded
    indirect part 1 % off; the bound here is 2·10⁻³ of the indirect term's own share (1.5·10⁻⁵ of
    the L1, 33× the measured rounding; the part scaled by 1.01 is 10⁻² of the share, 5× past it)."""
    loss_a, a, recordings = first_moment(True, 3)
    loss_b, b, _ = first_moment(False, 3)
    without = first_moment(False, 3, drop=INDIRECT)[1]
    assert recordings == {"direct": 1, "primary": 1, INDIRECT: 1, "interior": 1}, recordings
    assert np.isclose(loss_a, loss_b, rtol=1e-5)
    share = np.abs(b - without).sum()
    assert share > 1e-3 * np.abs(b).sum()  # the indirect term counts
    assert np.abs(a - b).sum() <= 2e-3 * share, (np.abs(a - b).sum() / share, share / np.abs(b).sum())


def test_a_frozen_loop_at_depth_3_is_the_same_loop_traced():
    """Four loop iterations at max_depth 3 (the shape moves; each part replays on new vertex
    buffers, batches and seeds) with the recorded parts and with the same parts traced: the same
    losses and shapes, bit for bit on LLVM (10⁻⁴ on CUDA, whose atomic adds reorder)."""
    runs = []
    for enabled in (True, False):
        exp, problem, engine, stage = setup(**SCENE)
        loop = iteration.Loop(exp.optimize, engine, 10, print, frozen=FrozenBatch(enabled))
        guides = iteration.GuideCache()
        with backend.optimization_threads():
            losses = []
            for it in range(4):
                losses.append(iteration.iterate(problem, loop, stage, guides, it).loss)
                problem.apply()
            runs.append((np.array(losses), np.asarray(problem.vertices()).copy(),
                         loop.frozen.parts[INDIRECT].n_recordings))
        problem.release()
    (a, Va, recorded), (b, Vb, _) = runs
    assert 1 <= recorded <= 2 and len(set(a)) == 4
    if mi.variant().startswith("cuda"):
        assert np.allclose(a, b, rtol=1e-4) and np.abs(Va - Vb).max() < 1e-4
    else:
        assert np.array_equal(a, b) and np.array_equal(Va, Vb)


def test_below_depth_3_the_indirect_part_records_nothing():
    """At max_depth 2 (every term listed, as by default) the indirect term is 0: its part runs no
    pass, records nothing and leaves the leaves' gradient at 0."""
    shapes = perturbed_shapes(6, 1, **{**SCENE, "max_depth": 2})
    for problem, engine, frozen, _, trial, V, edges, views, delta in shapes:
        leaf = vertex_leaf_written(problem, V)
        assert frozen.record(INDIRECT, problem, views, trial, engine.settings, edges=edges, delta=delta) == 0
        assert frozen.parts[INDIRECT].n_recordings == 0 and not np.any(np.asarray(dr.grad(leaf)))
