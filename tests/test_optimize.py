"""psdr optimize (resume after a hard kill, Ctrl-C, atomic outputs, skipped NaN updates) and
psdr evaluate (identical meshes, concentric spheres, bad inputs)."""
import copy
import csv
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from conftest import bit_reproducible, psdr_exit_code, run_cli
from psdr_cli.commands import evaluate as ev
from psdr_cli.config.limits import MAX_ITERATIONS
from psdr_cli.scene import meshes

TINY = {
    "name": "tiny", "seed": 3,
    "scene": {
        "film": {"width": 16, "height": 16}, "max_depth": 2,
        "cameras": [{"orbit": {"count": 3, "radius": 2.6, "elevation_deg": 20, "target": [0, 0, 0.4], "fov": 30}}],
        "emitters": [{"type": "sky", "sun_direction": [0.5, -0.4, 0.75], "sun_scale": 0.2}],
        "objects": [{"name": "bunny", "mesh": {"shape": "bunny", "size": 0.8, "faces": 400},
                     "bsdf": {"type": "diffuse", "reflectance": 0.6}}]},
    "estimator": {"spp": 1, "primary_spp": 1, "boundary_spp": 1, "terms": ["interior", "primary", "direct"]},
    "optimize": {"object": "bunny", "target": {"spp": 8}, "iterations": 12, "batch_size": 1,
                 "init": {"mesh": {"shape": "sphere", "radius": 0.3, "subdivisions": 2},
                          "transform": {"translate": [0, 0, 0.4]}},
                 "remesh": {"method": "instant", "initial": 150, "at": [6], "vertices": [250]},
                 "checkpoint_every": 4, "preview_views": [0]},
}


def write(tmp_path, data, name="tiny.yaml"):
    data = copy.deepcopy(data)
    data["output"] = str(tmp_path / "runs")
    path = tmp_path / name
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def log_rows(run):
    with open(run / "log.csv", newline="") as f:
        return list(csv.DictReader(f))


def saved_iteration(state: Path) -> int:
    try:
        with np.load(state) as z:
            return json.loads(bytes(z["meta"]).decode())["iteration"]
    except Exception:  # noqa: BLE001 - not written yet
        return -1


def default_sigint():
    """Ctrl-C as on a terminal: a test suite started in the background by a non-interactive shell
    ignores SIGINT, and a child would inherit that (Python then never raises KeyboardInterrupt)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def start(cfg, *args):
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    return subprocess.Popen([sys.executable, "-m", "psdr_cli", "optimize", str(cfg), *args], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, preexec_fn=default_sigint)


def wait_for_state(state: Path, at_least: int, proc, timeout: float = 300) -> int:
    t0 = time.time()
    while time.time() - t0 < timeout:
        it = saved_iteration(state)
        if it >= at_least:
            return it
        assert proc.poll() is None, proc.communicate()
        time.sleep(0.05)
    raise AssertionError("the run did not save its state in time")


@pytest.mark.slow
@bit_reproducible
def test_resume_after_hard_kill_continues_where_it_stopped(tmp_path, run_psdr):
    """kill -9 in the middle, then --resume: every iteration is logged exactly once, the run ends
    with final.ply, and the resumed iterations reproduce the uninterrupted run's losses (that run
    in this process: the killed and the resumed one are real processes)."""
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    full = write(tmp_path / "a", TINY)
    r = run_psdr("optimize", full)
    assert r.returncode == 0, r.stderr
    reference = [float(row["loss"]) for row in log_rows(tmp_path / "a" / "runs" / "tiny")]

    cfg = write(tmp_path / "b", TINY)
    run = tmp_path / "b" / "runs" / "tiny"
    proc = start(cfg)
    killed_at = wait_for_state(run / "state.npz", 3, proc)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert not (run / "final.ply").exists()
    # a kill during a write may leave an atomic write's hidden temporary, never a partial named file
    assert all(p.name.startswith(".") for p in run.rglob("*.tmp*")), list(run.rglob("*.tmp*"))
    saved = saved_iteration(run / "state.npz")
    assert saved >= killed_at
    r = run_cli("optimize", cfg, "--resume")
    assert r.returncode == 0, r.stderr
    assert not list(run.rglob("*.tmp*")), list(run.rglob("*.tmp*"))  # the resumed run cleared them
    rows = log_rows(run)
    assert [int(x["iteration"]) for x in rows] == list(range(12))
    info = json.loads((run / "optimize.json").read_text())
    assert info["resumed_from"] == saved and info["iterations"] == 12
    assert (run / "final.ply").exists() and (run / "checkpoints" / "iter_0012.ply").exists()
    assert (run / "loss.png").exists() and (run / "previews" / "iter_0012_view_000.png").exists()
    assert (run / "reference.ply").exists() and len(list((run / "targets").glob("view_*.exr"))) == 3
    assert {int(x["vertices"]) for x in rows[6:]} != {int(x["vertices"]) for x in rows[:6]}  # remeshed at 6
    losses = [float(x["loss"]) for x in rows]
    assert losses == reference  # one Dr.Jit thread: bit-reproducible (docs/optimize.md, Reproducibility)
    assert (run / "final.ply").read_bytes() == (tmp_path / "a" / "runs" / "tiny" / "final.ply").read_bytes()


@pytest.mark.slow
def test_ctrl_c_saves_and_exits_cleanly(tmp_path):
    cfg = write(tmp_path, TINY)
    run = tmp_path / "runs" / "tiny"
    proc = start(cfg, "--iterations", "400")
    wait_for_state(run / "state.npz", 2, proc)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err
    assert "--resume" in err and "Traceback" not in err
    assert saved_iteration(run / "state.npz") >= 2
    assert not list(run.rglob("*.tmp*"))


@pytest.mark.parametrize("freeze", [False, True], ids=["traced", "frozen"])
def test_nan_gradient_skips_the_update(tmp_path, monkeypatch, freeze):
    """A non-finite render (its loss and gradient) leaves the mesh untouched and is logged as
    skipped, on the traced path (the batch's images poisoned) and on the recorded one (the loss
    and its adjoint δ poisoned, as a NaN render makes them, before the recorded boundary parts).
    (A NaN in the vertex gradient alone does not reach the optimiser's variable: Mitsuba's
    LargeSteps solve drops it, measured; the loss is the signal the loop has.)"""
    import drjit as dr
    from psdr_cli import api
    from psdr_cli.experiment.load import load_experiment
    from psdr_cli.optimisation.frozen_batch import FrozenBatch
    from psdr_cli.rendering import estimate
    data = copy.deepcopy(TINY)
    data["optimize"].update(iterations=3, remesh={"method": "none"}, freeze=freeze)
    exp = load_experiment(write(tmp_path, data))
    real_images, real_batch = estimate.ad_images, FrozenBatch.__call__  # the loop's two paths
    calls = []

    def poisoned_images(scene, edges, views, terms, settings, pass_index=0, guides=None, one_by_one=False):
        images = real_images(scene, edges, views, terms, settings, pass_index, guides=guides, one_by_one=one_by_one)
        return [img * (dr.nan if pass_index == 1 else 1.0) for img in images]

    def poisoned_batch(self, problem, stage, views, iteration, settings, cfg):
        calls.append(iteration)
        loss, delta = real_batch(self, problem, stage, views, iteration, settings, cfg)
        poison = dr.nan if iteration == 1 else 1.0
        return loss * poison, delta * poison

    monkeypatch.setattr(estimate, "ad_images", poisoned_images)
    monkeypatch.setattr(FrozenBatch, "__call__", poisoned_batch)
    warnings = []
    res = api.optimize(exp, warn=warnings.append)
    rows = log_rows(exp.run_dir)
    assert calls == ([0, 1, 2] if freeze else [])  # the path under test ran
    assert [r["skipped"] for r in rows] == ["0", "1", "0"] and res.skipped == 1
    assert any("skipped" in w for w in warnings)
    V, _ = meshes.read_mesh_file(exp.run_dir / "final.ply")
    assert np.isfinite(V).all()


def test_atomic_path_keeps_the_old_file_on_failure(tmp_path):
    from psdr_cli.support.fileio import atomic_path
    target = tmp_path / "mesh.ply"
    target.write_text("old")
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            Path(tmp).write_text("half")
            raise RuntimeError("crash while writing")
    assert target.read_text() == "old" and list(tmp_path.iterdir()) == [target]


def test_evaluate_identical_and_concentric_spheres():
    V, F = meshes.sphere(0.6, subdivisions=5)
    d = ev.distance((V, F), (V, F), samples=20_000, seed=1)
    floor = ev.noise_floor((V, F), samples=20_000)
    assert d.chamfer_l1 < 0.01 and d.chamfer_l1 == pytest.approx(floor.chamfer_l1, rel=0.2)
    # concentric spheres r = 0.5 and 0.6; the reference (0.6) box has side 1.2 → gap 0.1/1.2
    V2, F2 = meshes.sphere(0.5, subdivisions=5)
    d = ev.distance((V2, F2), (V, F), samples=20_000, seed=1)
    gap = 0.1 / 1.2
    assert d.chamfer_l1 == pytest.approx(gap, abs=0.002 + floor.chamfer_l1)
    assert d.chamfer_l2 == pytest.approx(gap ** 2, rel=0.08)
    assert d.hausdorff == pytest.approx(gap, abs=0.02)


def test_evaluate_bad_inputs_are_one_line_errors(tmp_path, run_psdr):
    V, F = meshes.sphere(0.5, subdivisions=2)
    meshes.write_ply(tmp_path / "s.ply", V, F)
    cases = [
        (["--reference", tmp_path / "missing.ply", tmp_path / "s.ply"], "file not found"),
        (["--reference", tmp_path / "s.ply", tmp_path / "empty_run"], "no checkpoints"),
        (["--reference", tmp_path / "empty.ply", tmp_path / "s.ply"], "empty"),
        ([tmp_path / "s.ply"], "no reference mesh"),
    ]
    (tmp_path / "empty_run").mkdir()
    (tmp_path / "empty.ply").write_text("ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\n"
                                        "property float y\nproperty float z\nelement face 0\n"
                                        "property list uchar int vertex_indices\nend_header\n")
    for args, message in cases:
        r = run_psdr("evaluate", *args)
        assert r.returncode == 2 and message in r.stderr, (args, r.stderr)
        assert len(r.stderr.strip().splitlines()) == 1 and "Traceback" not in r.stderr


def test_evaluate_cli_on_meshes(tmp_path):
    V, F = meshes.sphere(0.6, subdivisions=4)
    V2, F2 = meshes.sphere(0.5, subdivisions=4)
    meshes.write_ply(tmp_path / "ref.ply", V, F)
    meshes.write_ply(tmp_path / "small.ply", V2, F2)
    r = run_cli("evaluate", "--reference", tmp_path / "ref.ply", tmp_path / "small.ply", tmp_path / "ref.ply",
                "--samples", "5000", "--json", tmp_path / "out.json")
    assert r.returncode == 0, r.stderr
    out = json.loads((tmp_path / "out.json").read_text())
    small, same = out["meshes"]
    assert small["chamfer_l1"] == pytest.approx(0.1 / 1.2, abs=0.005 + same["chamfer_l1"])
    assert same["chamfer_l1"] == pytest.approx(out["noise_floor"]["chamfer_l1"], rel=0.3)
    assert "noise floor" in r.stdout


@pytest.mark.slow
def test_albedo_and_environment_rotation_are_recovered(tmp_path):
    """With the true shape as the start, the joint unknowns move to the truth: albedo 0.3 → 0.6,
    environment rotation 20° → 0°."""
    from psdr_cli import api
    from psdr_cli.experiment.load import load_experiment
    data = copy.deepcopy(TINY)
    data["optimize"].update(iterations=40, batch_size=3, learning_rate=1e-6, remesh={"method": "none"},
                            init={"mesh": {"shape": "bunny", "size": 0.8, "faces": 400}},
                            albedo={"init": 0.3, "learning_rate": 0.05},
                            envmap_rotation={"axis": [0, 0, 1], "init_deg": 20, "learning_rate": 0.05})
    data["estimator"].update(spp=16, primary_spp=4, boundary_spp=4)
    data["optimize"]["target"] = {"spp": 256}  # L1 compares medians: keep both renders' noise low
    exp = load_experiment(write(tmp_path, data))
    api.optimize(exp, warn=lambda m: None)
    values = json.loads((exp.run_dir / "optimize.json").read_text())["values"]
    albedo, angle = np.array(values["albedo"]), float(values["envmap_angle"][0])
    assert np.abs(albedo - 0.6).max() < 0.1, albedo
    assert abs(np.degrees(angle)) < 8, np.degrees(angle)


def test_targets_from_images_on_disk(tmp_path, run_psdr):
    """EXR targets written by `psdr render` (cameras from their headers) drive the optimisation;
    a glob that matches nothing is a one-line error."""
    data = copy.deepcopy(TINY)
    cfg = write(tmp_path, data, "scene.yaml")
    r = run_psdr("render", cfg, "--spp", "8", "--out", tmp_path / "shots")
    assert r.returncode == 0, r.stderr
    data["optimize"].update(iterations=2, remesh={"method": "none"},
                            target={"images": str(tmp_path / "shots" / "tiny" / "render" / "view_*.exr")})
    r = run_psdr("optimize", write(tmp_path, data, "from_images.yaml"))
    assert r.returncode == 0, r.stderr
    run = tmp_path / "runs" / "tiny"
    assert (run / "final.ply").exists() and not (run / "reference.ply").exists()
    assert len(log_rows(run)) == 2
    data["optimize"]["target"] = {"images": str(tmp_path / "nothing_*.exr")}
    r = run_psdr("optimize", write(tmp_path, data, "bad.yaml"))
    assert r.returncode == 2 and "no file matches" in r.stderr and len(r.stderr.strip().splitlines()) == 1


def test_guided_optimisation_rebuilds_its_guides_on_schedule(tmp_path):
    """With estimator.guiding set, guides are built at iteration 0 and every guide_every
    iterations (their time is logged in seconds_guiding), and the run completes."""
    from psdr_cli import api
    from psdr_cli.experiment.load import load_experiment
    data = copy.deepcopy(TINY)
    data["estimator"].update(guiding="kdtree", edge_sort=True, kdtree={"initial_samples": 4096})
    data["optimize"].update(iterations=5, guide_every=2, remesh={"method": "none"})
    exp = load_experiment(write(tmp_path, data))
    api.optimize(exp, warn=lambda m: None)
    rows = log_rows(exp.run_dir)
    built = [float(r["seconds_guiding"]) > 0 for r in rows]
    assert built == [True, False, True, False, True], [r["seconds_guiding"] for r in rows]
    assert (exp.run_dir / "final.ply").exists()


def test_auto_guiding_builds_no_guide_in_the_loop(tmp_path):
    """guiding: auto on a film whose boundary pass (16² × 256 = 2¹⁶ lanes) `psdr grad` would guide:
    the optimisation loop runs unguided (no guide time, no guide memory in the log)."""
    from psdr_cli import api
    from psdr_cli.experiment.load import load_experiment
    from psdr_cli.guiding import auto
    data = copy.deepcopy(TINY)
    data["estimator"].update(guiding="auto", boundary_spp=256)
    data["optimize"].update(iterations=2, guide_every=1, remesh={"method": "none"})
    exp = load_experiment(write(tmp_path, data))
    assert auto.decide("auto", 16 * 16, 256)["direct"] == "kdtree"
    api.optimize(exp, warn=lambda m: None)
    rows = log_rows(exp.run_dir)
    assert [r["guide_bytes"] for r in rows] == ["0", "0"] and all(float(r["seconds_guiding"]) == 0 for r in rows)


def test_rgb_albedo_moments_survive_resume(tmp_path):
    """Adam moments of a vector-valued unknown (RGB albedo) are restored on --resume."""
    from psdr_cli import api
    from psdr_cli.experiment.load import load_experiment
    from psdr_cli.run_folder.state import State
    data = copy.deepcopy(TINY)
    data["scene"]["objects"][0]["bsdf"] = {"type": "diffuse", "reflectance": [0.6, 0.5, 0.4]}
    data["optimize"].update(iterations=2, remesh={"method": "none"}, albedo={"init": 0.3})
    exp = load_experiment(write(tmp_path, data))
    api.optimize(exp, warn=lambda m: None)
    saved = State.load(exp.run_dir / "state.npz")
    assert saved.adam["albedo"][0] == 2
    from psdr_cli.optimisation.problem import Problem, Shape, adam_import, adam_export
    problem = Problem(exp, Shape(saved.V, saved.F, u=saved.u, basis=saved.basis), None, saved.values)
    adam_import(problem.opt, "albedo", saved.adam["albedo"])
    t, m, v = adam_export(problem.opt, "albedo")
    assert t == 2 and np.allclose(m, saved.adam["albedo"][1]) and np.allclose(v, saved.adam["albedo"][2])
    problem.release()


#: TINY for 3 iterations without remeshing: the finished run that test_plain_rerun_of_a_finished_run_keeps_it and
#: test_resume_restarts_when_the_experiment_changed continue or restart (one run, module-scoped)
THREE = copy.deepcopy(TINY)
THREE["optimize"].update(iterations=3, remesh={"method": "none"})


@pytest.fixture(scope="module")
def three_iterations(tmp_path_factory):
    """A folder holding THREE's experiment file and its finished run (`psdr optimize` in this
    process: conftest.psdr_exit_code); tests work on a copy (:func:`copy_run`), never on it."""
    folder = tmp_path_factory.mktemp("three_iterations")
    assert psdr_exit_code(["optimize", write(folder, THREE)]) == 0
    return folder


def copy_run(folder: Path, tmp_path: Path) -> Path:
    """``folder`` copied into ``tmp_path``, its experiment file's output pointed at the copy."""
    shutil.copytree(folder, tmp_path, dirs_exist_ok=True)
    return write(tmp_path, THREE)


def test_fresh_run_moves_the_previous_run_aside(tmp_path):
    """A fresh start (no --resume) on a folder holding a run never deletes it: the run is moved
    aside whole, said in one line, and the new run starts from iteration 0 (its targets reused)."""
    from psdr_cli import api
    from psdr_cli.experiment.load import load_experiment
    data = copy.deepcopy(TINY)
    data["optimize"].update(iterations=2, remesh={"method": "none"}, checkpoint_every=1)
    exp = load_experiment(write(tmp_path, data))
    api.optimize(exp, warn=lambda m: None)
    before = (exp.run_dir / "final.ply").read_bytes()
    said = []
    api.optimize(exp, iterations=1, warn=said.append)
    kept = [p for p in exp.run_dir.parent.iterdir() if p.name.startswith(f"{exp.run_dir.name}.previous-")]
    assert len(kept) == 1 and any(str(kept[0]) in m for m in said), said
    assert (kept[0] / "final.ply").read_bytes() == before and (kept[0] / "checkpoints" / "iter_0002.ply").exists()
    assert not (exp.run_dir / "checkpoints" / "iter_0002.ply").exists()
    assert json.loads((exp.run_dir / "optimize.json").read_text())["iterations"] == 1


def test_plain_rerun_of_a_finished_run_keeps_it(tmp_path, three_iterations, run_psdr):
    """`psdr optimize cfg --iterations 1` (no --resume) on a finished run: exit 0, the finished
    run kept under a .previous- name with its log and state; --iterations below a saved run's
    count under --resume still refuses, and its message no longer recommends deleting."""
    data = THREE
    cfg = copy_run(three_iterations, tmp_path)
    run = tmp_path / "runs" / data["name"]
    rows = (run / "log.csv").read_text()
    r = run_psdr("optimize", cfg, "--iterations", "2", "--resume")
    assert r.returncode == 2 and "moved aside, not deleted" in r.stderr, r.stderr
    assert (run / "log.csv").read_text() == rows
    r = run_psdr("optimize", cfg, "--iterations", "1")
    assert r.returncode == 0, r.stderr
    kept = sorted(run.parent.glob(f"{data['name']}.previous-*"))
    assert len(kept) == 1 and "kept in" in r.stdout + r.stderr
    assert (kept[0] / "log.csv").read_text() == rows and (kept[0] / "state.npz").exists()


@pytest.mark.slow
def test_variants_time_budget_report_and_table2(tmp_path, run_psdr):
    """optimize.variants runs one folder per variant; optimize.seconds ends each run at the first
    iteration past the budget (and --resume then adds nothing); `psdr evaluate` on the experiment
    writes the side-by-side report and `psdr table2` the time split of every run. The iteration
    count is the largest psdr accepts, 10⁶: reaching it within the 4 s would take 4 µs an
    iteration, so the budget ends the run on any machine (400 iterations, as before, fitted in 4 s
    on a fast one and the count ended the run)."""
    data = copy.deepcopy(TINY)
    data["optimize"].update(iterations=MAX_ITERATIONS, seconds=4.0, remesh={"method": "none"}, checkpoint_every=50)
    data["optimize"]["variants"] = [{"label": "grid", "guiding": "grid"},
                                    {"label": "plain", "guiding": "none", "sampling": "light"}]
    cfg = write(tmp_path, data)
    r = run_psdr("optimize", cfg)
    assert r.returncode == 0, r.stderr
    assert "grid: guiding grid: direct grid" in r.stdout and "plain: guiding none" in r.stdout  # one line per run
    root = tmp_path / "runs" / "tiny"
    counts = {}
    for label in ("grid", "plain"):
        rows = log_rows(root / label)
        seconds = [float(row["seconds_total"]) for row in rows]
        # seconds_total is logged to 3 decimals: 3.9996 s reads 4.000
        assert len(rows) < MAX_ITERATIONS and seconds[-1] >= 3.9995 and all(s < 4.0005 for s in seconds[:-1])
        assert (root / label / "final.ply").exists()
        assert (root / label / "checkpoints" / f"iter_{len(rows):04d}.ply").exists()
        counts[label] = len(rows)
    assert int(log_rows(root / "grid")[0]["guide_bytes"]) > 0 == int(log_rows(root / "plain")[0]["guide_bytes"])
    r = run_psdr("optimize", cfg, "--resume", "--variant", "grid")
    assert r.returncode == 0, r.stderr
    assert len(log_rows(root / "grid")) == counts["grid"]
    r = run_psdr("optimize", cfg, "--variant", "nope")
    assert r.returncode == 2 and "--variant" in r.stderr and len(r.stderr.strip().splitlines()) == 1

    r = run_psdr("evaluate", cfg, "--samples", "2000")
    assert r.returncode == 0, r.stderr
    table = (root / "evaluate.md").read_text()
    assert "| grid |" in table and "| plain |" in table
    for name in ("chamfer.png", "meshes.png", "grid.ply", "plain.ply", "reference.ply", "evaluate.json"):
        assert (root / name).stat().st_size > 0, name
    report = json.loads((root / "evaluate.json").read_text())
    assert [run["iterations"] for run in report["runs"]] == [counts["grid"], counts["plain"]]

    r = run_psdr("table2", cfg, "--out", str(tmp_path / "table2.md"))
    assert r.returncode == 0, r.stderr
    text = (tmp_path / "table2.md").read_text()
    assert "| tiny | grid | 3 |" in text and "| tiny | plain | 3 |" in text and "Jumpy Dumpty" in text


def test_variant_labels_are_checked(tmp_path, run_psdr):
    data = copy.deepcopy(TINY)
    data["optimize"]["variants"] = [{"label": "a/b"}]
    r = run_psdr("optimize", write(tmp_path, data))
    assert r.returncode == 2 and "optimize.variants" in r.stderr and "plain folder name" in r.stderr
    data["optimize"]["variants"] = [{"label": "a"}, {"label": "a", "sampling": "dir"}]
    r = run_psdr("optimize", write(tmp_path, data))
    assert r.returncode == 2 and "unique" in r.stderr and len(r.stderr.strip().splitlines()) == 1
    data["optimize"]["variants"] = [{"label": "reference"}]
    r = run_psdr("optimize", write(tmp_path, data))
    assert r.returncode == 2 and "'reference' is taken" in r.stderr


def test_reports_refuse_unfinished_runs(tmp_path):
    """A run folder whose log has more rows than its optimize.json records (killed mid-run)
    is not reported as a finished run."""
    from psdr_cli.errors import PsdrError
    run = tmp_path / "run"
    run.mkdir()
    (run / "log.csv").write_text("iteration,loss,vertices,seconds_guiding,seconds_rendering,seconds_post,"
                                 "seconds_total,skipped,guide_bytes\n0,0.1,100,0,0.1,0,0.1,0,0\n1,0.1,100,0,0.1,0,0.2,0,0\n")
    with pytest.raises(PsdrError, match="unfinished"):
        ev.run_summary(run)
    (run / "optimize.json").write_text(json.dumps({"iterations": 2, "views": 3}))
    s = ev.run_summary(run)
    assert s["iterations"] == 2 and s["views"] == 3 and abs(s["seconds_rendering"] - 0.1) < 1e-12


def test_variant_experiments_share_the_targets(tmp_path):
    """A variant replaces estimator keys and the run seed; its targets keep the base seed."""
    from psdr_cli.experiment.load import parse_experiment
    from psdr_cli.run_folder.variant_folders import variant_experiments
    from psdr_cli.target_sources.rendered_mesh import target_key
    data = copy.deepcopy(TINY)
    data["optimize"]["variants"] = [{"label": "a", "sampling": "light"}, {"label": "b", "seed": 42, "edge_sort": True}]
    exp = parse_experiment(data, tmp_path / "tiny.yaml", cwd=tmp_path)
    (la, a), (lb, b) = variant_experiments(exp)
    assert (la, lb) == ("a", "b") and a.run_dir == exp.run_dir / "a" and b.run_dir == exp.run_dir / "b"
    assert a.estimator.sampling == "light" and a.estimator.edge_sort is False and a.seed == exp.seed
    assert b.estimator.sampling == exp.estimator.sampling and b.estimator.edge_sort is True and b.seed == 42
    ref = (np.zeros((3, 3)), np.zeros((1, 3), int))
    assert target_key(a, ref, 8) == target_key(b, ref, 8) == target_key(exp, ref, 8)
    assert [label for label, _ in variant_experiments(exp, ["b"])] == ["b"]


def test_resume_restarts_when_the_experiment_changed(tmp_path, three_iterations, run_psdr):
    """--resume continues a run of the same experiment (more iterations extend it) but starts
    afresh, with a warning, when a key the result depends on has changed."""
    data = copy.deepcopy(THREE)
    copy_run(three_iterations, tmp_path)
    run = tmp_path / "runs" / "tiny"
    data["optimize"]["iterations"] = 5
    r = run_psdr("optimize", write(tmp_path, data), "--resume")
    assert r.returncode == 0 and "changed" not in r.stderr and "resumed from 3" in r.stdout.replace("\n", " ")
    assert len(log_rows(run)) == 5
    data["optimize"]["learning_rate"] = 0.02
    r = run_psdr("optimize", write(tmp_path, data), "--resume")
    assert r.returncode == 0 and "changed since" in (r.stdout + r.stderr).replace("\n", " ")
    assert len(log_rows(run)) == 5 and "resumed from 0" in r.stdout.replace("\n", " ")


def test_a_failing_remesher_never_ends_a_run(tmp_path, monkeypatch):
    """Instant Meshes raising (as MeshLab's orientation filter did on a non-manifold result) at
    the initial and the scheduled remesh: the run falls back to the isotropic remesher, says so
    and finishes."""
    import pymeshlab
    from psdr_cli import api
    from psdr_cli.experiment.load import load_experiment
    from psdr_cli.geometry import remesh

    def broken(*args, **kwargs):
        raise pymeshlab.PyMeshLabException("Failed to apply filter: meshing_re_orient_faces_coherently")

    monkeypatch.setattr(remesh, "instant_meshes", broken)
    data = copy.deepcopy(TINY)
    data["optimize"]["iterations"] = 7
    exp = load_experiment(write(tmp_path, data))
    warnings = []
    res = api.optimize(exp, warn=warnings.append)
    assert res.iterations == 7 and res.final.exists()
    fallbacks = [w for w in warnings if "remesh (instant" in w]
    assert len(fallbacks) == 2 and fallbacks[1].startswith("iteration 6:")
    assert {int(r["vertices"]) for r in log_rows(exp.run_dir)[6:]} != {int(r["vertices"]) for r in log_rows(exp.run_dir)[:6]}


def test_redirected_output_gets_progress_lines_and_the_budget_stop_is_announced(tmp_path):
    """Not on a terminal: plain progress lines (iteration, loss, elapsed, ETA); a run ended by
    optimize.seconds says so. However slow the machine, the budget lets the first iteration run;
    however fast, 10⁶ iterations do not fit in 2 s (2 µs an iteration), so the budget ends it."""
    data = copy.deepcopy(TINY)
    data["optimize"].update(iterations=MAX_ITERATIONS, seconds=2.0, remesh={"method": "none"}, checkpoint_every=100)
    r = run_cli("optimize", write(tmp_path, data), "--log-every", "1")
    assert r.returncode == 0, r.stderr
    lines = [l for l in r.stderr.splitlines() if ": iteration " in l]
    assert lines and all(f"/{MAX_ITERATIONS}, loss " in l and "elapsed" in l and "ETA" in l for l in lines)
    assert [l.split("/")[0] for l in lines] == [f"optimize: iteration {i + 1}" for i in range(len(lines))]
    assert f"the time budget (optimize.seconds) ended the run after {len(lines)} iterations" in r.stdout


def test_plain_progress_lines_come_every_n_iterations_and_at_the_end():
    """LossBar off a terminal: a line at every multiple of ``every`` and one at the last iteration."""
    from psdr_cli import cli
    bar = cli.LossBar("optimize", every=3)
    bar.lines = True
    with cli.console.capture() as captured:
        bar.start(7)
        for i in range(7):
            bar.advance(1, 0.5 / (i + 1))
    lines = [l for l in captured.get().splitlines() if ": iteration " in l]
    assert [l.split(",")[0] for l in lines] == ["optimize: iteration 3/7", "optimize: iteration 6/7",
                                                 "optimize: iteration 7/7"]
    assert lines[0].startswith("optimize: iteration 3/7, loss 0.16667, elapsed 0 s, ETA ")


def test_optimize_under_an_exr_environment_map_does_not_hang(tmp_path):
    """mi.Bitmap reading an EXR deadlocks while Dr.Jit runs one thread (as psdr optimize does by
    default); environment maps are read with fileio instead."""
    from psdr_cli.support import fileio
    fileio.write_rgb_exr(tmp_path / "env.exr", np.full((8, 16, 3), 0.8, np.float32))
    data = copy.deepcopy(TINY)
    data["scene"]["emitters"] = [{"type": "envmap", "file": str(tmp_path / "env.exr")}]
    data["optimize"].update(iterations=2, remesh={"method": "none"})
    r = run_cli("optimize", write(tmp_path, data), timeout=240)
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "runs" / "tiny" / "final.ply").exists()


def test_mitsuba_engine_lowers_the_shape_error(tmp_path):
    """estimator.engine: mitsuba (Mitsuba's direct_projective in our loop: same targets, init,
    batches and LargeSteps) grows a small sphere towards a larger target sphere within a few
    iterations, and the loss falls."""
    from psdr_cli import api
    from psdr_cli.experiment.load import load_experiment
    data = copy.deepcopy(TINY)
    data["scene"]["objects"][0].update(mesh={"shape": "sphere", "radius": 0.35, "subdivisions": 2},
                                       transform={"translate": [0, 0, 0.4]})
    data["estimator"] = {"engine": "mitsuba", "mitsuba_spp": 4}
    data["optimize"]["init"]["mesh"]["radius"] = 0.2
    data["optimize"].update(iterations=12, batch_size=3, learning_rate=0.1, remesh={"method": "none"})
    exp = load_experiment(write(tmp_path, data))
    api.optimize(exp, warn=lambda m: None)
    reference = ev.load(exp.run_dir / "reference.ply")
    before = ev.distance(ev.load(exp.run_dir / "checkpoints" / "iter_0000.ply"), reference, 5000).chamfer_l1
    after = ev.distance(ev.load(exp.run_dir / "final.ply"), reference, 5000).chamfer_l1
    assert after < 0.9 * before, (before, after)
    losses = [float(r["loss"]) for r in log_rows(exp.run_dir)]
    assert np.mean(losses[-3:]) < np.mean(losses[:3]), losses


def test_l1_adjoint_from_an_independent_render_removes_the_sign_correlation():
    """Each lane is a pixel I = θ·X (X: mean of 2 exponential samples, E[X] = 1) at θ = 1 with
    target 0.7, so the noise-free L1 loss has derivative sign(1 − 0.7)·E[X] = 1. The sign taken
    from I's own samples gives E[sign(X − 0.7)·X] (the gradient of the noisy render's loss, far
    from 1); the sign of an independent 256-sample render P gives ≈ 1. The value is P's L1."""
    import drjit as dr
    import mitsuba as mi
    from psdr_cli.losses.l1 import l1_loss
    from psdr_cli.support import backend
    backend.select_variant("auto")
    rng = np.random.default_rng(0)
    n = 200_000
    X = rng.exponential(size=(n, 2)).mean(1)
    P = rng.exponential(size=(n, 256)).mean(1)
    target = mi.Float(np.full(n, 0.7, np.float32))
    grads = []
    for adjoint in (None, mi.Float(P.astype(np.float32))):
        theta = mi.Float(1.0)
        dr.enable_grad(theta)
        loss = l1_loss(theta * mi.Float(X.astype(np.float32)), target, adjoint)
        dr.backward(loss)
        grads.append(float(dr.grad(theta)[0]))
        if adjoint is not None:
            assert abs(float(loss[0]) - np.mean(np.abs(P - 0.7))) < 1e-4
    assert grads[0] < 0.8, grads            # E[sign(X − 0.7)·X] ≈ 0.67 for this X
    assert abs(grads[1] - 1.0) < 0.02, grads


def test_adjoint_spp_optimisation_runs_and_is_checked(tmp_path, run_psdr):
    """optimize.adjoint_spp > 0 runs (the loss logged is the adjoint render's L1) and a negative
    value is a one-line error naming the key."""
    data = copy.deepcopy(TINY)
    data["optimize"].update(iterations=3, adjoint_spp=4, remesh={"method": "none"})
    r = run_psdr("optimize", write(tmp_path, data))
    assert r.returncode == 0, r.stderr
    assert len(log_rows(tmp_path / "runs" / "tiny")) == 3
    data["optimize"]["adjoint_spp"] = -1
    r = run_psdr("optimize", write(tmp_path, data, "bad.yaml"))
    assert r.returncode != 0 and "optimize.adjoint_spp" in r.stderr and "Traceback" not in r.stderr


def test_learning_rate_final_decays_geometrically_after_the_last_remesh():
    """lr is constant up to the last remesh before the end, then decays geometrically to
    learning_rate_final at the last iteration; unset, it stays constant."""
    from psdr_cli.config.optimize_section import OptimizeConfig, RemeshConfig
    from psdr_cli.optimisation.iteration import learning_rate_at
    cfg = OptimizeConfig(object="x", learning_rate=0.1, learning_rate_final=0.01,
                         remesh=RemeshConfig("instant", 800, (100, 200, 400), (1500, 2500, 4000)))
    assert learning_rate_at(cfg, 0, 300) == 0.1 and learning_rate_at(cfg, 200, 300) == 0.1
    assert np.isclose(learning_rate_at(cfg, 299, 300), 0.01)
    assert np.isclose(learning_rate_at(cfg, 250, 300), 0.1 * 0.1 ** (50 / 99))
    assert np.isclose(learning_rate_at(cfg, 150, 200), 0.1 * 0.1 ** (50 / 99))  # s = 100 when 200 is not reached
    assert learning_rate_at(OptimizeConfig(object="x", learning_rate=0.1), 299, 300) == 0.1


def test_learning_rate_final_changes_the_run_and_is_checked(tmp_path, run_psdr):
    """A run with learning_rate_final takes smaller late steps than one without (its vertices move
    less over the last three iterations), and a non-positive value is a one-line error."""
    from psdr_cli import api
    from psdr_cli.experiment.load import load_experiment
    finals = {}
    for label, extra in (("const", {}), ("decay", {"learning_rate_final": 0.001})):
        data = copy.deepcopy(TINY)
        data["name"] = label
        data["optimize"].update(iterations=6, remesh={"method": "none"}, checkpoint_every=3, **extra)
        exp = load_experiment(write(tmp_path, data, f"{label}.yaml"))
        api.optimize(exp, warn=lambda m: None)
        mid = ev.load(exp.run_dir / "checkpoints" / "iter_0003.ply")
        finals[label] = (mid, ev.load(exp.run_dir / "final.ply"))
    (mid_c, end_c), (mid_d, end_d) = finals["const"], finals["decay"]
    assert np.abs(end_d[0] - mid_d[0]).max() < 0.5 * np.abs(end_c[0] - mid_c[0]).max()
    data["optimize"]["learning_rate_final"] = 0
    r = run_psdr("optimize", write(tmp_path, data, "bad.yaml"))
    assert r.returncode != 0 and "optimize.learning_rate_final" in r.stderr and "Traceback" not in r.stderr


def test_downsampled_targets_are_what_a_lower_resolution_render_estimates(tmp_path):
    """With the box pixel filter, the mean of k × k pixels of a W × H render is the pixel of a
    W/k × H/k render (optimize.downsample): they agree to the renders' noise, while taking every
    k-th pixel instead does not."""
    from psdr_cli.experiment.load import load_experiment
    from psdr_cli.optimisation.problem import stage_experiment
    from psdr_cli.optimisation.stages import downsample
    from psdr_cli.rendering.render import render_view
    from psdr_cli.scene.build import build_scene
    from psdr_cli.support import backend
    data = copy.deepcopy(TINY)
    data["scene"]["film"] = {"width": 32, "height": 32}
    data["optimize"].update(downsample=[2, 1])
    exp = load_experiment(write(tmp_path, data))
    backend.activate(exp)
    fine = render_view(build_scene(exp), 0, 256, seed=1)
    coarse = render_view(build_scene(stage_experiment(exp, 0)), 0, 1024, seed=2)
    assert coarse.shape == (16, 16, 3) and fine.shape == (32, 32, 3)
    box = np.abs(downsample(fine, 2) - coarse).mean()
    picked = np.abs(fine[::2, ::2] - coarse).mean()
    assert box < 0.5 * picked, (box, picked)
    assert box < 0.05 * coarse.mean(), (box, coarse.mean())


@pytest.mark.slow
@bit_reproducible
def test_coarse_to_fine_and_lambda_schedule_resume_exactly(tmp_path):
    """downsample [2, 1] and lambda [40, 10] with a remesh at 4 (stage 0 on 8² images, stage 1 on
    16²): a run stopped at the stage change and resumed repeats the uninterrupted run's losses and
    final mesh, and the previews of both stages have the film's size."""
    from PIL import Image
    from psdr_cli import api
    from psdr_cli.experiment.load import load_experiment
    data = copy.deepcopy(TINY)
    data["optimize"].update(iterations=8, checkpoint_every=2, downsample=[2, 1], remesh={
        "method": "instant", "initial": 150, "at": [4], "vertices": [250]}, **{"lambda": [40, 10]})
    runs = {}
    for label in ("whole", "stopped"):
        data["name"] = label
        exp = load_experiment(write(tmp_path, data, f"{label}.yaml"))
        if label == "stopped":
            api.optimize(exp, iterations=4, warn=lambda m: None)
            api.optimize(exp, resume=True, warn=lambda m: None)
        else:
            api.optimize(exp, warn=lambda m: None)
        runs[label] = exp.run_dir
    assert [r["loss"] for r in log_rows(runs["whole"])] == [r["loss"] for r in log_rows(runs["stopped"])]
    assert (runs["whole"] / "final.ply").read_bytes() == (runs["stopped"] / "final.ply").read_bytes()
    sizes = {Image.open(p).size for p in (runs["whole"] / "previews").glob("iter_*_view_000.png")}
    assert len(sizes) == 1, sizes  # stage 0's 8² previews are enlarged to the 16² film's size


def test_stage_lists_are_checked_again_when_code_changes_the_experiment(tmp_path):
    """An experiment changed after parsing (as the benchmarks do: another remesh schedule, another
    film) is checked again by optimize: one-line errors, not a traceback or a silent mismatch."""
    from dataclasses import replace
    from psdr_cli import api
    from psdr_cli.config.optimize_section import RemeshConfig
    from psdr_cli.errors import PsdrError
    from psdr_cli.experiment.load import load_experiment
    data = copy.deepcopy(TINY)
    data["optimize"].update(downsample=[2, 1], **{"lambda": [40, 10]})
    exp = load_experiment(write(tmp_path, data))
    fewer = replace(exp, optimize=replace(exp.optimize, remesh=RemeshConfig("instant", 150, (), ())))
    with pytest.raises(PsdrError, match=r"optimize.lambda: expected one value, or a list of 1"):
        api.optimize(fewer, warn=lambda m: None)
    odd = replace(exp, scene=replace(exp.scene, width=15))
    with pytest.raises(PsdrError, match=r"optimize.downsample\[0\]: 2 does not divide the film's 15×16"):
        api.optimize(odd, warn=lambda m: None)


def test_the_loop_guiding_line_names_no_psdr_guide_under_the_mitsuba_engine(tmp_path):
    """The line `psdr optimize` prints per run says what the loop guides with: under
    ``estimator.engine: mitsuba`` no psdr guide is built (Mitsuba samples its own boundaries),
    whatever ``estimator.guiding`` says."""
    from psdr_cli.commands.optimize import loop_guiding_line
    from psdr_cli.config.options import with_estimator
    from psdr_cli.experiment.load import load_experiment
    data = copy.deepcopy(TINY)
    data["estimator"].update(engine="mitsuba", guiding="kdtree")
    exp = load_experiment(write(tmp_path, data))
    assert loop_guiding_line("", exp) == "guiding none: estimator.engine mitsuba samples its own boundaries"
    assert loop_guiding_line("psdr", with_estimator(exp, engine="psdr")).startswith("psdr: guiding kdtree: direct kdtree")
