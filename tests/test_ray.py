"""``psdr optimize --ray``: a two-variant sweep on a local two-CPU Ray instance gives the sequential
result (shared and copied run folders), a worker killed mid-run is retried and resumes, and
without Ray ``--ray`` is a one-line error naming the install command.

The tests marked ``ray`` need the optional extra (``pip install 'psdr[ray]'``; ``make test``
installs it) and are skipped without it."""
import copy
import csv
import importlib.util
import json
import os
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from conftest import run_cli
from test_optimize import TINY, saved_iteration, write

HAVE_RAY = importlib.util.find_spec("ray") is not None
needs_ray = pytest.mark.skipif(not HAVE_RAY, reason="Ray is not installed (pip install 'psdr[ray]')")

SWEEP = copy.deepcopy(TINY)
SWEEP["optimize"].update(iterations=4, checkpoint_every=2, remesh={"method": "instant", "initial": 150})
SWEEP["optimize"]["variants"] = [{"label": "grid", "guiding": "grid"},
                                 {"label": "plain", "guiding": "none", "sampling": "light", "seed": 5}]


@pytest.fixture(scope="module")
def local_ray():
    import ray
    ray.init(num_cpus=2, include_dashboard=False, logging_level="WARNING")
    yield ray
    ray.shutdown()


@pytest.fixture(scope="module")
def sequential_sweep(tmp_path_factory):
    """(experiment, {label: OptimizeResult}) of :data:`SWEEP` run sequentially, once for the
    sweeps compared with it."""
    return sequential(tmp_path_factory.mktemp("sweep"), SWEEP)


def files_of(root: Path) -> list:
    return sorted(p.relative_to(root).as_posix() for p in root.rglob("*") if p.is_file())


def rows(run: Path) -> list:
    with open(run / "log.csv", newline="") as f:
        return list(csv.DictReader(f))


def sequential(tmp_path, data):
    from psdr_cli import api
    from psdr_cli.experiment.load import load_experiment
    (tmp_path / "seq").mkdir()
    exp = load_experiment(write(tmp_path / "seq", data))
    return exp, dict(api.optimize_variants(exp, warn=lambda m: None))


def assert_same_runs(a: Path, b: Path, labels, rtol=1e-4):
    """Same files in every run folder; same losses, vertex counts and final meshes (the Dr.Jit
    thread count differs between the two: float32 sums in another order)."""
    from psdr_cli.scene import meshes
    assert files_of(a) == files_of(b)
    for label in labels:
        ra, rb = rows(a / label), rows(b / label)
        assert [r["iteration"] for r in ra] == [r["iteration"] for r in rb]
        assert [r["vertices"] for r in ra] == [r["vertices"] for r in rb]
        np.testing.assert_allclose([float(r["loss"]) for r in rb], [float(r["loss"]) for r in ra], rtol=rtol)
        Va, Fa = meshes.read_mesh_file(a / label / "final.ply")
        Vb, Fb = meshes.read_mesh_file(b / label / "final.ply")
        assert (Fa == Fb).all()
        np.testing.assert_allclose(Vb, Va, atol=1e-3)
        info = json.loads((b / label / "optimize.json").read_text())
        assert info["final"] == str(b / label / "final.ply") and info["iterations"] == len(ra)


@pytest.mark.ray
@needs_ray
@pytest.mark.parametrize("files", ["shared", "copy"])
def test_ray_sweep_matches_the_sequential_run(tmp_path, local_ray, sequential_sweep, files):
    from psdr_cli import api
    from psdr_cli.commands.sweep import RayOptions
    from psdr_cli.experiment.load import load_experiment
    seq_exp, seq = sequential_sweep
    (tmp_path / "ray").mkdir()
    exp = load_experiment(write(tmp_path / "ray", SWEEP))
    events = []

    class Line:
        def __init__(self, label):
            self.label = label

        def start(self, total, done=0):
            events.append((self.label, "start", total, done))

        def advance(self, n, loss=None):
            events.append((self.label, "advance", n, loss))

    results = dict(api.optimize_variants(exp, warn=lambda m: None, progress=Line,
                                         ray=RayOptions(files=files, sync_seconds=0.0)))
    assert sorted(results) == ["grid", "plain"]
    for label in results:
        assert results[label].final == exp.run_dir / label / "final.ply"
        np.testing.assert_allclose(results[label].losses, seq[label].losses, rtol=1e-4)
        assert (label, "start", 4, 0) in events and sum(e[1] == "advance" and e[0] == label for e in events) == 4
    assert_same_runs(seq_exp.run_dir, exp.run_dir, ["grid", "plain"])
    # no temporary files left (each run's .<label>.lock file stays by design: run_folder.layout.lock_run)
    assert not [p for p in exp.run_dir.rglob(".*") if p.suffix != ".lock"]
    if files == "shared":
        return  # the workers run optimize() itself there (test_optimize checks a fresh start keeps a run)
    # a fresh sweep over finished runs moves them aside (as optimize() does), never deletes them
    finals = {label: (exp.run_dir / label / "final.ply").read_bytes() for label in results}
    said = []
    dict(api.optimize_variants(exp, iterations=1, warn=said.append, ray=RayOptions(files=files, sync_seconds=0.0)))
    for label, final in finals.items():
        kept = list(exp.run_dir.glob(f"{label}.previous-*"))
        assert len(kept) == 1 and (kept[0] / "final.ply").read_bytes() == final, (label, said)
        assert len(rows(exp.run_dir / label)) == 1


def task_processes(title: str) -> list:
    """Pids of the Ray workers running a task (Ray sets their process title to ray::NAME)."""
    pids = []
    for proc in Path("/proc").iterdir():
        try:
            if proc.name.isdigit() and (proc / "cmdline").read_bytes().startswith(title.encode()):
                pids.append(int(proc.name))
        except OSError:
            pass
    return pids


@pytest.mark.ray
@needs_ray
@pytest.mark.slow
def test_a_killed_worker_is_retried_and_resumes(tmp_path, local_ray):
    """kill -9 of the workers once a run is in its middle: Ray retries the tasks, which resume
    from their saved states; every iteration is logged once and the losses are the uninterrupted
    run's (to the resume tolerance of test_optimize)."""
    from psdr_cli import api
    from psdr_cli.commands.sweep import RayOptions
    from psdr_cli.experiment.load import load_experiment
    data = copy.deepcopy(SWEEP)
    data["optimize"]["iterations"] = 16
    seq_exp, seq = sequential(tmp_path, data)
    (tmp_path / "ray").mkdir()
    exp = load_experiment(write(tmp_path / "ray", data))
    killed, warnings = [], []

    def killer():
        t0 = time.time()
        while time.time() - t0 < 300:
            states = [saved_iteration(exp.run_dir / label / "state.npz") for label in ("grid", "plain")]
            if any(2 <= s < 12 for s in states):  # kill every running task (the other run may be anywhere)
                for pid in task_processes("ray::optimize_task"):
                    os.kill(pid, 9)
                    killed.append(pid)
                return
            if any(s >= 12 for s in states):
                return
            time.sleep(0.05)

    watcher = threading.Thread(target=killer)
    watcher.start()
    results = dict(api.optimize_variants(exp, warn=warnings.append, ray=RayOptions(files="shared")))
    watcher.join()
    assert killed, "the runs ended before the workers could be killed"
    assert any("resumes from the saved state" in w for w in warnings), warnings
    for label in ("grid", "plain"):
        assert [int(r["iteration"]) for r in rows(exp.run_dir / label)] == list(range(16))
        np.testing.assert_allclose([float(r["loss"]) for r in rows(exp.run_dir / label)], seq[label].losses, rtol=2e-3)
        assert (exp.run_dir / label / "final.ply").exists()
        assert results[label].iterations == 16


def test_ray_missing_is_a_one_line_error(tmp_path, monkeypatch):
    """Without Ray installed, --ray says how to install it (a stand-in 'ray' module that fails
    to import plays the missing package)."""
    fake = tmp_path / "noray"
    fake.mkdir()
    (fake / "ray.py").write_text("raise ImportError('No module named ray')\n")
    cfg = write(tmp_path, SWEEP)
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(filter(None, [str(fake), os.environ.get("PYTHONPATH")])))
    r = run_cli("optimize", cfg, "--ray")
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert "pip install 'psdr[ray]'" in r.stderr
    assert not (tmp_path / "runs").exists()


def test_ray_address_is_checked(tmp_path):
    r = run_cli("optimize", write(tmp_path, SWEEP), "--ray", "--ray-files", "nfs")
    assert r.returncode == 2 and "--ray-files" in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr


@pytest.mark.ray
@needs_ray
def test_ray_compare_matches_the_sequential_run(tmp_path, local_ray):
    """`psdr compare --ray` (reference and each variant one task) writes the sequential run's files
    with the same numbers (equal samples: no timing in the result)."""
    from psdr_cli import api
    from psdr_cli.commands.sweep import RayOptions
    from psdr_cli.experiment.load import parse_experiment
    from test_guiding import SHADOW
    data = copy.deepcopy(SHADOW)
    data["estimator"] = {"spp": 4, "boundary_spp": 16, "terms": ["direct"], "kdtree": {"initial_samples": 4096}}
    data["compare"] = {"terms": ["direct"], "trials": 1, "reference_passes": 16, "variants": [
        {"label": "none", "passes": 4}, {"label": "kdtree", "guiding": "kdtree", "passes": 4}]}
    results = {}
    for mode in ("seq", "ray"):
        data["output"] = str(tmp_path / mode)
        exp = parse_experiment(copy.deepcopy(data), tmp_path / "shadow.yaml", cwd=tmp_path)
        results[mode] = api.compare(exp, ray=RayOptions() if mode == "ray" else None)
    seq, ray_ = results["seq"], results["ray"]
    assert files_of(seq.folder) == files_of(ray_.folder)
    assert [r.variant.label for r in ray_.rows] == ["none", "kdtree"]
    np.testing.assert_allclose(ray_.reference_rel_mse, seq.reference_rel_mse, rtol=1e-3)
    for a, b in zip(seq.rows, ray_.rows):
        assert a.passes == b.passes == [4]
        np.testing.assert_allclose(b.rel_mse, a.rel_mse, rtol=1e-3, atol=1e-6)
        np.testing.assert_allclose(b.image, a.image, rtol=1e-3, atol=1e-5)
