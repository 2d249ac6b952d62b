"""The recorded part of an iteration (issue 38, psdr_cli/frozen_batch.py): a replay gives what
tracing the same function gives, for batches it was not recorded on; a changed structure (a new
scene after a remesh, another film) is recorded again and still gives the traced result; and the
loop's iteration with it is the traced iteration of before, up to rounding."""
from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np
import yaml

import psdr_cli
from conftest import bit_reproducible
from psdr_cli import api, backend, iteration, meshes
from psdr_cli.engines import Engine
from psdr_cli.estimate import Settings
from psdr_cli.frozen_batch import FrozenBatch, refusal
from psdr_cli.problem import Problem, Shape
from psdr_cli.run_folder.log import read_log
from psdr_cli.stages import stage_of

CONFIG = Path(__file__).resolve().parents[1] / "configs" / "reconstruct_bunny.yaml"


def setup(subdivisions: int = 2, width: int | None = None):
    exp = psdr_cli.load_experiment(CONFIG)
    backend.activate(exp)
    if width is not None:
        exp = replace(exp, scene=replace(exp.scene, width=width, height=width))
    V, F = meshes.sphere(0.4, subdivisions)
    problem = Problem(exp, Shape(V + [0, 0, 0.42], F), None, {})
    engine = Engine(Settings.from_experiment(exp, loop=True))
    W, H = exp.scene.width, exp.scene.height
    rng = np.random.default_rng(1)
    targets = [rng.uniform(0.0, 0.6, (H, W, 3)).astype(np.float32) for _ in exp.scene.cameras]
    return exp, problem, engine, stage_of(problem, targets, engine.settings, engine.terms)


def batch_gradient(fb: FrozenBatch, problem, stage, engine, cfg, views, it):
    """(ℓ, δ, the vertex leaf's gradient) of one call, on leaves written afresh."""
    problem.applied = None
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


def iteration_gradient(frozen: bool, it: int):
    exp, problem, engine, stage = setup()
    loop = iteration.Loop(exp.optimize, engine, 10, print, frozen=FrozenBatch() if frozen else None)
    u0 = np.asarray(problem.opt["u"]).copy()
    with backend.optimization_threads():
        step = iteration.iterate(problem, loop, stage, iteration.GuideCache(), it)
    assert not frozen or loop.frozen.n_recordings == 1  # the frozen part ran
    moved = np.asarray(problem.opt["u"]) - u0
    problem.release()
    return step, moved


def test_the_frozen_iteration_is_the_traced_iteration():
    """One loop iteration (interior, primary and direct terms, an adjoint render) with the frozen
    part and without it: the same loss and the same update, up to the rounding of the camera rays
    (the table's rays against Mitsuba's sensor objects)."""
    a, moved_a = iteration_gradient(True, 3)
    b, moved_b = iteration_gradient(False, 3)
    assert not a.skipped and not b.skipped
    assert np.isclose(a.loss, b.loss, rtol=1e-5)
    # Adam's first step is lr · sign(g) where |g| is not tiny: the steps agree almost everywhere
    agree = np.isclose(moved_a, moved_b, rtol=1e-3, atol=1e-6)
    assert agree.mean() > 0.99, agree.mean()


def test_runs_the_frozen_part_cannot_serve_are_named():
    exp, problem, engine, stage = setup()
    cfg = exp.optimize
    assert "adjoint" in refusal(problem, stage, replace(cfg, adjoint_spp=0), engine, engine.settings, 4)
    assert "freeze" in refusal(problem, stage, replace(cfg, freeze=False), engine, engine.settings, 4)
    mitsuba = Engine(replace(engine.settings, estimator=replace(engine.settings.estimator, engine="mitsuba")))
    assert refusal(problem, stage, cfg, mitsuba, engine.settings, 4) is not None
    assert "wider" in refusal(problem, stage, cfg, engine, engine.settings, 10 ** 4)
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
def test_a_frozen_run_resumes_exactly_across_a_remesh(tmp_path):
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
    assert runs["whole"][0] == runs["stopped"][0] and len(runs["whole"][0]) == 6
    assert (runs["whole"][1] / "final.ply").read_bytes() == (runs["stopped"][1] / "final.ply").read_bytes()
