"""The recorded part of an iteration (issue 38, psdr_cli/optimisation/frozen_batch.py): a replay gives what
tracing the same function gives, for batches it was not recorded on; a changed structure (a new
scene after a remesh, another film) is recorded again and still gives the traced result; and the
loop's iteration with it is the traced iteration of before, up to rounding."""
from __future__ import annotations

import gc
import sys
from dataclasses import dataclass, replace
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest
import yaml

import psdr_cli
from conftest import bit_reproducible
from psdr_cli import api
from psdr_cli.config.estimator_section import EstimatorConfig
from psdr_cli.estimators.boundary_sampling import edge_list
from psdr_cli.estimators.recording import Recording
from psdr_cli.optimisation import iteration
from psdr_cli.optimisation.engines import Engine
from psdr_cli.optimisation.frozen_batch import FrozenBatch, refusal
from psdr_cli.optimisation.problem import Problem, Shape, adam_export
from psdr_cli.optimisation.stages import stage_of
from psdr_cli.rendering.estimate import Settings
from psdr_cli.run_folder.log import read_log
from psdr_cli.scene import meshes
from psdr_cli.support import backend
from psdr_cli.support.jitarray import jit_array

CONFIG = Path(__file__).resolve().parents[1] / "configs" / "reconstruct_bunny.yaml"


def setup(subdivisions: int = 2, width: int | None = None, shadowed: bool = False, jitter: int | None = None,
          max_depth: int | None = None):
    """The demo's experiment on a sphere, or (``shadowed``) on two spheres, one in the other's
    shadow under the sun (a convex shape casts no shadow: the direct term is 0 there); ``jitter``
    (a seed): every vertex coordinate moved by one float32 step (ulp) up or down at random, a
    change of the size of the rays' rounding; ``max_depth``: paths that long, with every term
    (the indirect one too, from depth 3: light between the two spheres)."""
    exp = psdr_cli.load_experiment(CONFIG)
    backend.activate(exp)
    if width is not None:
        exp = replace(exp, scene=replace(exp.scene, width=width, height=width))
    if max_depth is not None:
        exp = replace(exp, scene=replace(exp.scene, max_depth=max_depth),
                      estimator=replace(exp.estimator, terms=EstimatorConfig().terms))
    V, F = meshes.sphere(0.4, subdivisions)
    V = V + [0, 0, 0.42]
    if shadowed:
        sun = np.array([0.5, -0.4, 0.75]) / np.linalg.norm([0.5, -0.4, 0.75])
        V, F = np.concatenate([0.6 * V, 0.4 * V + 0.55 * sun]), np.concatenate([F, F + len(V)])
    if jitter is not None:
        V32 = V.astype(np.float32)
        up = np.random.default_rng(jitter).integers(0, 2, V32.shape).astype(bool)
        V = np.where(up, np.nextafter(V32, np.float32(np.inf)), np.nextafter(V32, np.float32(-np.inf))).astype(np.float64)
    problem = Problem(exp, Shape(V, F), None, {})
    engine = Engine(Settings.from_experiment(exp, loop=True))
    W, H = exp.scene.width, exp.scene.height
    rng = np.random.default_rng(1)
    targets = [rng.uniform(0.0, 0.6, (H, W, 3)).astype(np.float32) for _ in exp.scene.cameras]
    return exp, problem, engine, stage_of(problem, targets, engine.settings, engine.terms)


def batch_gradient(fb: FrozenBatch, problem, stage, engine, cfg, views, it):
    """(ℓ, δ, the vertex leaf's gradient) of one call, on leaves written afresh."""
    problem.invalidate()
    values, leaves = problem.apply_leaves()
    loss, delta = fb(problem, stage, views, it, engine.settings, cfg)
    g = dr.grad(leaves[problem.key])
    dr.eval(loss, delta, g)
    return float(loss[0]), np.asarray(delta), np.asarray(g, np.float64)


def assert_same(a, b):
    if not mi.variant().startswith("cuda"):  # CUDA's atomic scatter-adds are not reproducible
        assert a[0] == b[0] and np.array_equal(a[1], b[1]) and np.array_equal(a[2], b[2])
    else:
        assert np.isclose(a[0], b[0], rtol=1e-6) and np.array_equal(a[1], b[1])
        assert np.abs(a[2] - b[2]).max() <= 1e-5 * np.abs(b[2]).max()


def test_replays_give_the_traced_result_and_a_new_structure_records_again():
    exp, problem, engine, stage = setup()
    cfg = exp.optimize
    assert refusal(problem, stage, cfg, engine, engine.settings, cfg.batch_size) is None
    frozen, traced = FrozenBatch(), FrozenBatch(enabled=False)
    with backend.optimization_threads():
        counts = []
        for it in range(6):  # batches of 4 of the 12 views: the recordings do not grow with them
            views = iteration.batch_views(0, it, len(stage.arrays), cfg.batch_size)
            a = batch_gradient(frozen, problem, stage, engine, cfg, views, it)
            b = batch_gradient(traced, problem, stage, engine, cfg, views, it)
            assert np.abs(b[2]).sum() > 0 and b[0] > 0
            assert_same(a, b)
            counts.append(frozen.n_recordings)
        # the second call records once more (Dr.Jit makes the literals that changed opaque), then none
        assert counts[1] <= 2 and counts[-1] == counts[1] and traced.n_recordings == 0
        # a remesh: a new scene with another vertex count is recorded again, and replayed right
        problem.release()
        exp, problem, engine, stage = setup(subdivisions=3)
        for it in (6, 7, 8):
            views = iteration.batch_views(0, it, len(stage.arrays), cfg.batch_size)
            assert_same(batch_gradient(frozen, problem, stage, engine, cfg, views, it),
                        batch_gradient(traced, problem, stage, engine, cfg, views, it))
        assert counts[-1] < frozen.n_recordings <= counts[-1] + 2
        before = frozen.n_recordings
        # another film (a stage's downsampling)
        problem.release()
        exp, problem, engine, stage = setup(width=32)
        views = iteration.batch_views(0, 9, len(stage.arrays), cfg.batch_size)
        assert_same(batch_gradient(frozen, problem, stage, engine, cfg, views, 9),
                    batch_gradient(traced, problem, stage, engine, cfg, views, 9))
        assert frozen.n_recordings == before + 1
    problem.release()


class Interrupter:
    """Raises KeyboardInterrupt at the ``moment``-th Python line run inside a recorded part's call
    (:class:`psdr_cli.estimators.recording.Recording`: a SIGINT's KeyboardInterrupt arrives at the next line
    the interpreter runs); ``lines`` counts them (``moment`` None: count only)."""

    def __init__(self, monkeypatch, moment: int | None = None):
        self.moment, self.lines = moment, 0
        real = Recording.__call__

        def traced_call(recording, shape, *args):
            sys.settrace(self.trace)
            try:
                return real(recording, shape, *args)
            finally:
                sys.settrace(None)
        monkeypatch.setattr(Recording, "__call__", traced_call)

    def trace(self, frame, event, arg):
        if event in ("call", "line"):
            self.lines += 1
            if self.lines == self.moment:
                raise KeyboardInterrupt
        return self.trace


def first_iteration(frozen: bool = True):
    """The loop's first iteration on the shadowed spheres of a fresh :func:`setup` (with the
    recorded parts: each records on this call): (loss, Adam's first moment of the vertex latent),
    or the exception it raised; the problem is released after it."""
    exp, problem, engine, stage = setup(shadowed=True)
    loop = iteration.Loop(exp.optimize, engine, 10, print, frozen=FrozenBatch() if frozen else None)
    try:
        with backend.optimization_threads():
            step = iteration.iterate(problem, loop, stage, iteration.GuideCache(), 0)
        if frozen:
            assert loop.frozen.parts["primary"].n_recordings == 1 and loop.frozen.parts["direct"].n_recordings == 1
        return step.loss, adam_export(problem.opt, "u")[1]
    except BaseException as error:  # noqa: BLE001 - what reaches the loop is the result
        return error
    finally:
        problem.release()


def test_a_ctrl_c_at_any_moment_of_a_recording_reaches_the_loop_as_keyboard_interrupt():
    """A Ctrl-C at 30 moments spread over the recordings of the loop's three recorded parts
    (interior, direct, primary): the loop gets KeyboardInterrupt every time, never Dr.Jit's
    RuntimeError (some moments wrap it in four of them: "record(): error encountered while
    recording a frozen function", the internal error users saw); the process survives what the
    interrupted recordings leave for the garbage collector (it aborted at the 59th of 60 moments
    of a batch call before the collector was kept out of recordings); and an iteration recorded
    afterwards is the traced one."""
    first_iteration()  # (its kernels compiled: the later calls run the same lines)
    with pytest.MonkeyPatch.context() as mp:
        counter = Interrupter(mp)
        first_iteration()
    assert counter.lines > 1000
    errors = []
    for moment in np.linspace(1, counter.lines, 30).astype(int):
        with pytest.MonkeyPatch.context() as mp:
            Interrupter(mp, int(moment))
            error = first_iteration()
        if not isinstance(error, tuple):
            errors.append(error)
            assert isinstance(error, KeyboardInterrupt), (moment, counter.lines, repr(error))
    assert len(errors) >= 28
    gc.collect()
    (loss_a, m_a), (loss_b, m_b) = first_iteration(), first_iteration(frozen=False)
    assert np.isclose(loss_a, loss_b, rtol=1e-5) and np.abs(m_a - m_b).sum() <= 1e-4 * np.abs(m_b).sum()


def test_interrupted_recordings_leave_nothing_that_aborts_a_later_one():
    """60 batch calls of the interior part, each interrupted at another moment of its recording,
    one after the other in this process, then a whole one: every interrupt reaches the caller as
    KeyboardInterrupt, and the process is still alive (before the garbage collector was kept out
    of recordings, a collection during the 50th recording freed an array mapped from numpy that an
    earlier interrupted one had left in a cycle, and Dr.Jit aborted the process: "RecordThreadState::
    enqueue_host_func(): this function cannot be recorded!"); the whole call is the traced one."""
    exp, problem, engine, stage = setup(shadowed=True)
    cfg = exp.optimize
    views = iteration.batch_views(0, 0, len(stage.arrays), cfg.batch_size)
    with backend.optimization_threads():
        reference = batch_gradient(FrozenBatch(enabled=False), problem, stage, engine, cfg, views, 0)
        batch_gradient(FrozenBatch(), problem, stage, engine, cfg, views, 0)  # (kernels compiled)
        with pytest.MonkeyPatch.context() as mp:
            counter = Interrupter(mp)
            batch_gradient(FrozenBatch(), problem, stage, engine, cfg, views, 0)
        for moment in np.linspace(1, counter.lines, 60).astype(int):
            with pytest.MonkeyPatch.context() as mp:
                Interrupter(mp, int(moment))
                with pytest.raises(KeyboardInterrupt):
                    batch_gradient(FrozenBatch(), problem, stage, engine, cfg, views, 0)
        assert_same(batch_gradient(FrozenBatch(), problem, stage, engine, cfg, views, 0), reference)
    problem.release()


def loop_losses(enabled: bool | None, jitter: int | None = None, iterations: int = 8):
    """(losses, final vertices, recordings) of ``iterations`` loop iterations on the shadowed
    spheres (:func:`setup`, ``jitter`` its seed): with the recorded parts (``enabled`` true), the
    same parts traced (false), or the traced iteration of before (None: no leaves, Mitsuba's sensor
    objects)."""
    exp, problem, engine, stage = setup(shadowed=True, jitter=jitter)
    loop = iteration.Loop(exp.optimize, engine, 10, print, frozen=None if enabled is None else FrozenBatch(enabled))
    guides = iteration.GuideCache()
    V0 = np.asarray(problem.vertices()).copy()
    with backend.optimization_threads():
        losses = []
        for it in range(iterations):
            losses.append(iteration.iterate(problem, loop, stage, guides, it).loss)
            problem.apply()  # as the loop does after each step
        V = np.asarray(problem.vertices()).copy()
    assert np.abs(V - V0).max() > 1e-3  # the shape moved
    problem.release()
    return np.array(losses), V, loop.frozen.n_recordings if loop.frozen else 0


def test_a_frozen_loop_is_the_traced_loop_while_the_shape_moves():
    """Eight loop iterations (Adam steps move the shape: the recorded part replays on new vertex
    buffers, written by the large-steps solve as the loop writes them) with the recorded part and
    with the same part traced: the same losses and the same shape, bit for bit (on LLVM).

    And the traced loop of before (no leaves, Mitsuba's sensor objects), whose rays round
    differently from the camera table's: a ray grazing a silhouette hits or misses, a pixel's
    sign(P − T) turns, and the loop amplifies that from step to step, by an amount that depends on
    the CPU's vector width (measured 1.8·10⁻⁴ at the fifth loss with 16 lanes, 4·10⁻⁵ with 8). The
    tolerance is measured in the same run: the loop of before started from the same shape with
    every vertex coordinate one float32 step off (four seeds), a change of the rays' rounding size;
    the recorded loop may differ from the loop of before by at most 4× the largest of those
    differences so far (a running maximum: differences only grow through the loop). With the
    recorded primary part halved the third loss is 1.4·10⁻³ off, 3× past that bound at 16 lanes."""
    a, Va, recorded = loop_losses(True)
    b, Vb, _ = loop_losses(False)
    assert 3 <= recorded <= 6  # each part recorded once or twice, replayed on the later iterations
    if mi.variant().startswith("cuda"):
        assert np.allclose(a, b, rtol=1e-4) and np.abs(Va - Vb).max() < 1e-4
    else:
        assert np.array_equal(a, b) and np.array_equal(Va, Vb)
    c = loop_losses(None)[0]
    rounding = np.max([np.abs(loop_losses(None, seed)[0] - c) / c for seed in range(4)], axis=0)
    bound = 4 * np.maximum.accumulate(rounding)
    off = np.abs(a - c) / c
    assert (off[:5] <= bound[:5]).all(), (off, bound)


def iteration_gradient(frozen: bool, it: int, adjoint_spp: int | None = None):
    exp, problem, engine, stage = setup(shadowed=True)
    cfg = exp.optimize if adjoint_spp is None else replace(exp.optimize, adjoint_spp=adjoint_spp)
    loop = iteration.Loop(cfg, engine, 10, print, frozen=FrozenBatch() if frozen else None)
    u0 = np.asarray(problem.opt["u"]).copy()
    with backend.optimization_threads():
        step = iteration.iterate(problem, loop, stage, iteration.GuideCache(), it)
    if frozen:  # the three parts ran: the interior term's, the direct term's and the primary term's
        assert loop.frozen.interior.n_recordings == 1 and loop.frozen.parts["direct"].n_recordings == 1
        assert loop.frozen.parts["primary"].n_recordings == 1
    moved = np.asarray(problem.opt["u"]) - u0
    m = adam_export(problem.opt, "u")[1]  # Adam's first moment after its first step: (1 − β₁)·g
    problem.release()
    return step, moved, m


@pytest.mark.parametrize("adjoint_spp", [None, 0], ids=["adjoint-render", "no-adjoint-render"])
def test_the_frozen_iteration_is_the_traced_iteration(adjoint_spp):
    """One loop iteration (interior, primary and direct terms, with the experiment's adjoint
    render or without one, the sign then taken from the AD render itself; two spheres, one in the
    other's shadow, so that the direct term counts) with the recorded parts and without them: the
    same loss, gradient and update, up to the rounding of the camera rays (the table's rays
    against Mitsuba's sensor objects). Measured at 16, 8 and 4 lanes (PSDR_LLVM_LANES): the loss
    ≤ 5.3·10⁻⁷ apart (bound 10⁻⁵), the gradient's L1 ≤ 1.7·10⁻⁷ (bound 10⁻⁴), every update
    within the 10⁻³ (bound 99 %): a single iteration does not amplify the rays' rounding as the
    loop does (test_a_frozen_loop_is_the_traced_loop_while_the_shape_moves)."""
    a, moved_a, ga = iteration_gradient(True, 3, adjoint_spp)
    b, moved_b, gb = iteration_gradient(False, 3, adjoint_spp)
    assert not a.skipped and not b.skipped
    assert np.isclose(a.loss, b.loss, rtol=1e-5)
    # the gradient itself (each term's share counts), and Adam's step lr·g/|g|
    assert np.abs(ga - gb).sum() <= 1e-4 * np.abs(gb).sum(), np.abs(ga - gb).sum() / np.abs(gb).sum()
    agree = np.isclose(moved_a, moved_b, rtol=1e-3, atol=1e-6)
    assert agree.mean() > 0.99, agree.mean()


def test_runs_the_frozen_part_cannot_serve_are_named():
    exp, problem, engine, stage = setup()
    cfg = exp.optimize
    assert refusal(problem, stage, replace(cfg, adjoint_spp=0), engine, engine.settings, 4) is None
    assert "freeze" in refusal(problem, stage, replace(cfg, freeze=False), engine, engine.settings, 4)
    mitsuba = Engine(replace(engine.settings, estimator=replace(engine.settings.estimator, engine="mitsuba")))
    assert refusal(problem, stage, cfg, mitsuba, engine.settings, 4) is not None
    assert "wider" in refusal(problem, stage, cfg, engine, engine.settings, 10 ** 4)
    problem.opt["albedo"] = mi.Float(0.5, 0.5, 0.5)  # an unknown besides the shape
    assert "besides the shape" in refusal(problem, stage, cfg, engine, engine.settings, 4)
    problem.release()


def test_freeze_is_read_from_the_experiment(tmp_path, run_psdr):
    path = tmp_path / "x.yaml"
    path.write_text(CONFIG.read_text().replace("  adjoint_spp: 4", "  adjoint_spp: 4\n  freeze: false"))
    assert psdr_cli.load_experiment(path).optimize.freeze is False
    assert psdr_cli.load_experiment(CONFIG).optimize.freeze is True
    path.write_text(CONFIG.read_text().replace("  adjoint_spp: 4", "  adjoint_spp: 4\n  freeze: 3"))
    r = run_psdr("optimize", str(path), "--iterations", "1")
    assert r.returncode != 0 and "optimize.freeze" in r.stderr and "Traceback" not in r.stderr


@bit_reproducible
def test_a_frozen_run_resumes_exactly_across_a_remesh(tmp_path, monkeypatch):
    """A run on the frozen path (an adjoint render, a remesh at 3: a new scene, recorded again)
    stopped at the remesh and resumed repeats the uninterrupted run's losses and final mesh (the
    resumed process records afresh). (The scene is test_optimize's TINY one, whose traced terms'
    kernels the suite compiles anyway.)"""
    data = {
        "name": "f", "seed": 3, "output": str(tmp_path / "runs"),
        "scene": {"film": {"width": 16, "height": 16}, "max_depth": 2,
                  "cameras": [{"orbit": {"count": 3, "radius": 2.6, "elevation_deg": 20, "target": [0, 0, 0.4],
                                         "fov": 30}}],
                  "emitters": [{"type": "sky", "sun_direction": [0.5, -0.4, 0.75], "sun_scale": 0.2}],
                  "objects": [{"name": "bunny", "mesh": {"shape": "bunny", "size": 0.8, "faces": 400},
                               "bsdf": {"type": "diffuse", "reflectance": 0.6}}]},
        "estimator": {"spp": 1, "primary_spp": 1, "boundary_spp": 1, "terms": ["interior", "primary", "direct"]},
        "optimize": {"object": "bunny", "target": {"spp": 8}, "iterations": 6, "batch_size": 1, "adjoint_spp": 4,
                     "init": {"mesh": {"shape": "sphere", "radius": 0.3, "subdivisions": 2},
                              "transform": {"translate": [0, 0, 0.4]}},
                     "remesh": {"method": "instant", "initial": 150, "at": [3], "vertices": [250]},
                     "checkpoint_every": 3, "preview_views": [0]}}
    calls = []
    original = FrozenBatch.__call__

    def counted(self, *args):
        calls.append(1)
        return original(self, *args)
    monkeypatch.setattr(FrozenBatch, "__call__", counted)
    runs = {}
    for label in ("whole", "stopped"):
        data["name"] = label
        path = tmp_path / f"{label}.yaml"
        path.write_text(yaml.safe_dump(data))
        exp = psdr_cli.load_experiment(path)
        if label == "stopped":
            api.optimize(exp, iterations=3, warn=lambda m: None)
            api.optimize(exp, resume=True, warn=lambda m: None)
        else:
            api.optimize(exp, warn=lambda m: None)
        runs[label] = [float(r["loss"]) for r in read_log(exp.run_dir / "log.csv")], exp.run_dir
    assert len(calls) == 12  # every iteration of both runs took the frozen path
    assert runs["whole"][0] == runs["stopped"][0] and len(runs["whole"][0]) == 6
    assert (runs["whole"][1] / "final.ply").read_bytes() == (runs["stopped"][1] / "final.ply").read_bytes()


def perturbed_shapes(seed: int, trials: int = 4, deform=None, **scene):
    """The part tests' set-up: yields (problem, engine, a recorded and a traced FrozenBatch, the
    trial, the sphere's vertices jittered (and ``deform(trial, V)`` when given), their edge table,
    a batch, a fixed δ) on a prepared problem (``scene``: :func:`setup`'s options), in the
    optimisation's thread setting."""
    exp, problem, engine, stage = setup(**scene)
    frozen, traced = FrozenBatch(), FrozenBatch(enabled=False)
    V0 = np.asarray(problem.vertices())
    rng = np.random.default_rng(seed)
    delta = mi.Float(rng.choice([-1.0, 1.0], 4 * 3 * exp.scene.width * exp.scene.height) * 1e-4)
    with backend.optimization_threads():
        for fb in (frozen, traced):
            fb.prepare(problem, stage)
        for trial in range(trials):
            V = V0 + rng.normal(0.0, 0.01, V0.shape)
            V = deform(trial, V) if deform is not None else V
            problem.scene.objects["bunny"].vertices = V
            edges = edge_list(problem.scene, engine.settings.estimator, False)
            views = iteration.batch_views(0, trial, len(stage.arrays), exp.optimize.batch_size)
            yield problem, engine, frozen, traced, trial, V, edges, views, delta
    problem.invalidate()
    problem.release()


def moved_vertex(V, k: float):
    """``V`` with its first vertex moved to centre + k·(v − centre) (the sphere's centre): k = 0.1
    sinks it into a deep dimple whose faces fold back against their neighbours (n0·n1 < 0); k =
    −1.3 pushes it through the far side (intersection curves)."""
    centre = np.array([0.0, 0.0, 0.42])
    V = V.copy()
    V[0] = centre + k * (V[0] - centre)
    return V


def vertex_leaf_written(problem, V):
    """The scene's vertex leaf after writing ``V`` as the loop writes vertices: through the
    optimiser's latent and the large-steps solve (a frozen call on a vertex buffer written from a
    numpy array each call replayed wrong results on Dr.Jit 1.5: docs/benchmarks/iteration_time.md,
    stop 52)."""
    problem.opt["u"] = problem.steps.to_differential(jit_array(mi.Float, np.ravel(V)))
    problem.invalidate()
    _, leaves = problem.apply_leaves()
    return leaves[problem.key]


def assert_replayed(grads):
    """The recorded part's gradient (``grads[0]``) is the traced part's (``grads[1]``), nonzero."""
    assert np.abs(grads[1]).sum() > 0
    if mi.variant().startswith("cuda"):
        assert np.abs(grads[0] - grads[1]).max() <= 1e-5 * np.abs(grads[1]).max()
    else:
        assert np.array_equal(grads[0], grads[1])


def test_the_direct_part_replays_right_for_any_number_of_edges():
    """The direct term's recorded part (edges as arrays padded to a power of two, drawn by
    LengthDistribution) against the same part traced, on shapes whose edge tables differ in
    length: the same gradient each time, and no recording per edge count. The vertices are
    written as the loop writes them (:func:`vertex_leaf_written`)."""
    counts = []
    for problem, engine, frozen, traced, trial, V, edges, views, delta in perturbed_shapes(2):
        counts.append(edges.count)
        grads = []
        for fb in (frozen, traced):
            leaf = vertex_leaf_written(problem, V)
            assert fb.serves("direct", problem, views, engine.settings, edges, None)
            fb.record("direct", problem, views, trial, engine.settings, edges=edges, delta=delta)
            grads.append(np.asarray(dr.grad(leaf), np.float64))
        assert_replayed(grads)
    assert len(set(counts)) > 1, counts
    assert frozen.parts["direct"].n_recordings <= 2


#: Per trial of the primary part's test: the settings' changes (sampling, depth) and the dimple
PRIMARY_TRIALS = ({}, {"primary_sampling": "jump"}, {"max_depth": 1}, {"dimple": True})


def test_the_primary_part_replays_right_for_any_number_of_curves():
    """The primary term's recorded part (each view's curves selected on the host, the batch's
    curves as arrays padded to a power of two, drawn on the device) against the same part traced,
    on shapes whose curve lists differ in length: the same gradient each time, and no recording per
    count; and against the term's traced pass (``estimate_views``), which projects with the same
    camera table: the same up to rounding. The trials cover edge weights other than 1 (``jump``
    sampling on the flat-shaded sphere: a wrongly packed weight would change 1/p), one scattering
    depth (smooth-silhouette selection) and folds (a dimple: the fold normals' recording).
    The vertices are written as the loop writes them."""
    counts, folds = [], []
    deform = lambda trial, V: moved_vertex(V, 0.1) if PRIMARY_TRIALS[trial].get("dimple") else V  # noqa: E731
    for problem, engine, frozen, traced, trial, V, edges, views, delta in perturbed_shapes(3, deform=deform):
        change = {k: v for k, v in PRIMARY_TRIALS[trial].items() if k != "dimple"}
        settings = engine.settings
        if "max_depth" in change:
            settings = replace(settings, max_depth=change["max_depth"])
        if "primary_sampling" in change:
            settings = settings.with_estimator(primary_sampling=change["primary_sampling"])
        grads = []
        for fb in (frozen, traced, None):  # None: the term's traced pass
            leaf = vertex_leaf_written(problem, V)
            if fb is None:
                images = Engine(settings).images(problem, edges, views, trial, terms=("primary",))
                dr.backward(dr.sum(delta * dr.concat(images)))
            else:
                assert fb.serves("primary", problem, views, settings, edges, None)
                counts.append(fb.record("primary", problem, views, trial, settings, edges=edges, delta=delta))
            grads.append(np.asarray(dr.grad(leaf), np.float64))
        assert_replayed(grads[:2])
        # the same arithmetic: rounding only (measured ≤ 6·10⁻⁸; half the term would give 0.5)
        error = np.abs(grads[1] - grads[2]).sum() / np.abs(grads[2]).sum()
        assert error <= 1e-5, (trial, error)
        folds.append(any(shape.folds for shape in frozen.parts["primary"].recording.fns))
    assert len(set(counts)) > 1, counts
    assert folds == [False, False, False, True], folds  # the dimple's folds were recorded
    # one recording per structure: plain, depth 1 (max_depth is recorded) and folds; not per count
    assert frozen.parts["primary"].n_recordings <= 4


def test_the_primary_part_leaves_intersection_curves_to_the_traced_term():
    """A vertex pushed through the far side of the sphere: its faces cross the sphere's, the
    primary term's curves include intersection curves, and the recorded part refuses."""
    pierced = perturbed_shapes(4, 1, lambda trial, V: moved_vertex(V, -1.3))
    for problem, engine, frozen, _, _, V, edges, views, _ in pierced:
        vertex_leaf_written(problem, V)
        assert not frozen.serves("primary", problem, views, engine.settings, edges, None)


@dataclass(frozen=True)
class ProbeShape:
    """A structure for :class:`Recording` (what it needs of one: a scene id, hashable)."""
    scene_id: int


def test_ctrl_c_while_recording_is_an_interrupt_and_the_next_call_records_afresh():
    """Dr.Jit reports an exception raised while a frozen function records as a RuntimeError; a
    Ctrl-C there must reach the optimisation loop as KeyboardInterrupt (it saves and exits 130;
    the real process: test_optimize.py::test_ctrl_c_saves_and_exits_cleanly, when its signal
    lands during a recording), and the function cut short is not replayed."""
    backend.activate(psdr_cli.load_experiment(CONFIG))
    interrupts = [True]

    def body(shape, x):
        y = x * shape.scene_id
        if interrupts and interrupts.pop():
            raise KeyboardInterrupt
        return y

    recording = Recording(body)
    with pytest.raises(KeyboardInterrupt):
        recording(ProbeShape(3), mi.Float([1.0, 2.0]))
    assert np.array_equal(np.asarray(recording(ProbeShape(3), mi.Float([1.0, 2.0]))), [3.0, 6.0])
    assert np.array_equal(np.asarray(recording(ProbeShape(3), mi.Float([4.0, 5.0]))), [12.0, 15.0])


def test_only_an_interrupt_that_caused_the_error_is_an_interrupt():
    """interrupt_in follows what an error was raised from, and what it was raised during unless
    that was suppressed: an error of its own raised while a Ctrl-C was being handled is not one."""
    from psdr_cli.estimators.recording import interrupt_in

    def raised(during_interrupt: bool, suppress: bool):
        try:
            try:
                raise KeyboardInterrupt
            except KeyboardInterrupt as interrupt:
                if during_interrupt and suppress:
                    raise RuntimeError("own error") from None
                if during_interrupt:
                    raise RuntimeError("own error")
                raise RuntimeError("record(): error encountered while recording") from interrupt
        except RuntimeError as error:
            return error
    assert isinstance(interrupt_in(raised(False, False)), KeyboardInterrupt)  # raised from it
    assert isinstance(interrupt_in(raised(True, False)), KeyboardInterrupt)   # raised while it stopped the call
    assert interrupt_in(raised(True, True)) is None                             # explicitly not from it
    assert interrupt_in(RuntimeError("plain")) is None
