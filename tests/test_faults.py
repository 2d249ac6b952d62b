"""Adversarial inputs and faults (issue 14): each bad input or fault gives exit code 2 (usage and
input errors), one ``error:`` line on stderr naming the file, key or option, no traceback and no
output under a final name; concurrent writers are refused; a torn log.csv is tolerated; a run
killed and resumed reproduces the uninterrupted one, guided runs with albedo included.

The commands run in-process (``psdr_cli.cli.run``) where they can, to keep this module fast."""
import copy
import csv
import fcntl
import math
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

from conftest import bit_reproducible, experiment
from psdr_cli import cli
from psdr_cli.errors import PsdrError
from psdr_cli.run_folder.layout import RunFiles, lock_run
from psdr_cli.run_folder.log import read_log
from psdr_cli.support import fileio


def psdr(capsys, *args):
    """(exit code, stdout, non-empty stderr lines) of ``psdr ARGS`` run in this process."""
    capsys.readouterr()
    code = cli.run([str(a) for a in args])
    captured = capsys.readouterr()
    return code, captured.out, [ln for ln in captured.err.splitlines() if ln.strip()]


def assert_one_line_error(code, out, err, expected, code_expected=2):
    assert code == code_expected, (code, err)
    assert len(err) == 1, err
    assert err[0].startswith("error: "), err
    assert expected in err[0], err[0]
    assert "Traceback" not in out + "\n".join(err)


def ply_ascii(path, V, F):
    lines = ["ply", "format ascii 1.0", f"element vertex {len(V)}", "property float x", "property float y",
             "property float z", f"element face {len(F)}", "property list uchar int vertex_indices", "end_header"]
    lines += [" ".join(repr(float(c)) for c in v) for v in V] + [f"3 {a} {b} {c}" for a, b, c in F]
    path.write_text("\n".join(lines) + "\n")


TETRA_V = [[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]
TETRA_F = [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]]


def obj(d, i=0):
    return d["scene"]["objects"][i]


def edit(fn):
    """An experiment (dict) changed by ``fn(d, tmp)``."""
    def make(tmp):
        d = experiment()
        fn(d, tmp)
        return d
    return make


def text(s):
    return lambda tmp: s


def mesh_file(name, V, F=TETRA_F):
    def fn(d, tmp):
        ply_ascii(tmp / name, V, F)
        obj(d)["mesh"] = {"file": name}
    return fn


def optimize_section(**remesh):
    def fn(d, tmp):
        d["optimize"] = {"object": "ball", "remesh": remesh}
    return fn


# (id, experiment factory, command-line arguments, text the error line must contain)
YAML = "name: t\nscene:\n  film: {width: 8, height: 8, width: 9}\n"
CONFIG_CASES = [
    ("duplicate_key", text(YAML), [], "duplicate key 'width'"),
    ("duplicate_scene_block", lambda tmp: yaml.safe_dump(experiment(), sort_keys=False) + "scene: {}\n", [],
     "duplicate key 'scene'"),
    ("duplicate_key_in_list_item", text("scene:\n  objects:\n    - {name: a, name: b}\n"), [], "duplicate key 'name'"),
    ("top_level_list", text("- 1\n- 2\n"), [], "expected a mapping"),
    ("vertex_1e39", edit(mesh_file("big.ply", TETRA_V[:3] + [[0, 0, 1e39]])), [], "scene.objects[0].mesh.file"),
    ("vertex_1e20", edit(mesh_file("far.ply", TETRA_V[:3] + [[0, 0, 1e20]])), [], "beyond ±1e+06"),
    ("scale_1e39", edit(lambda d, t: obj(d).update(transform={"scale": 1e39})), [], "scene.objects[0].transform.scale"),
    ("translate_nan", edit(lambda d, t: obj(d).update(transform={"translate": [0, math.nan, 0]})), [],
     "scene.objects[0].transform.translate: expected 3 finite numbers, got [0, nan, 0]"),
    ("translate_huge", edit(lambda d, t: obj(d).update(transform={"translate": [0, 1e30, 0]})), [],
     "transform.translate: expected 3 numbers within ±1e+06"),
    ("radiance_1e39", edit(lambda d, t: d["scene"]["emitters"][0].update(radiance=1e39)), [],
     "scene.emitters[0].radiance: expected"),
    ("radiance_inf_list", edit(lambda d, t: d["scene"]["emitters"][0].update(radiance=[1, math.inf, 1])), [],
     "scene.emitters[0].radiance: expected 3 finite numbers"),
    ("radiance_negative", edit(lambda d, t: d["scene"]["emitters"][0].update(radiance=-2)), [],
     "scene.emitters[0].radiance: expected non-negative values <= 1e+09, got [-2, -2, -2]"),
    ("envmap_scale_1e300", edit(lambda d, t: d["scene"]["emitters"].append({"type": "envmap", "file": "x.exr",
                                                                            "scale": 1e300})), [],
     "scene.emitters[1].scale"),
    ("sky_scale_1e39", edit(lambda d, t: d["scene"]["emitters"].append({"type": "sky", "sun_direction": [0, 0, 1], "sun_scale": 1e39})), [],
     "scene.emitters[1].sun_scale"),
    ("camera_origin_1e300", edit(lambda d, t: d["scene"]["cameras"][0].update(origin=[0, -1e300, 2])), [],
     "scene.cameras[0].origin"),
    ("area_size_1e7", edit(lambda d, t: d["scene"]["emitters"][0].update(size=[1e7, 1])), [],
     "scene.emitters[0].size"),
    ("reflectance_negative", edit(lambda d, t: obj(d).update(bsdf={"type": "diffuse", "reflectance": -1})), [],
     "scene.objects[0].bsdf.reflectance: expected values in [0, 1], got number -1"),
    ("reflectance_above_one", edit(lambda d, t: obj(d).update(bsdf={"type": "diffuse", "reflectance": [0.5, 1.5, 0]})),
     [], "scene.objects[0].bsdf.reflectance: expected values in [0, 1]"),
    ("base_color_above_one", edit(lambda d, t: obj(d).update(bsdf={"type": "principled", "base_color": 3})), [],
     "scene.objects[0].bsdf.base_color"),
    ("ior_zero", edit(lambda d, t: obj(d).update(bsdf={"type": "roughdielectric", "int_ior": 0})), [],
     "scene.objects[0].bsdf.int_ior"),
    ("radius_inf", edit(lambda d, t: obj(d)["mesh"].update(radius=math.inf)), [], "scene.objects[0].mesh.radius"),
    ("name_internal_emitter", edit(lambda d, t: obj(d).update(name="@emitter_00")), [],
     "scene.objects[0].name: '@emitter_00' is reserved"),
    ("name_type", edit(lambda d, t: obj(d, 1).update(name="type")), [],
     "scene.objects[1].name: 'type' is reserved"),
    ("spp_1e12", edit(lambda d, t: d.update(estimator={"spp": 10 ** 12})), [], "estimator.spp: expected an integer <="),
    ("spp_paths", edit(lambda d, t: (d["scene"]["film"].update(width=4096, height=4096), d.update(estimator={"spp": 1024}))),
     [], "estimator.spp: 1024 samples per pixel × 4096×4096 pixels"),
    ("max_depth_100000", edit(lambda d, t: d["scene"].update(max_depth=100000)), [], "scene.max_depth: expected an integer <= 64"),
    ("film_100000", edit(lambda d, t: d["scene"]["film"].update(width=100000)), [], "scene.film.width: expected an integer <="),
    ("grid_100000x100x100", edit(lambda d, t: d.update(estimator={"grid": {"resolution": [100000, 100, 100]}})), [],
     "estimator.grid.resolution: 1000000000 cells exceed"),
    ("grid_samples", edit(lambda d, t: d.update(estimator={"grid": {"resolution": [256, 64, 64],
                                                                    "samples_per_cell": 4096}})), [],
     "estimator.grid.samples_per_cell"),
    ("kdtree_initial_samples", edit(lambda d, t: d.update(estimator={"kdtree": {"initial_samples": 10 ** 10}})), [],
     "estimator.kdtree.initial_samples"),
    ("remesh_initial_5000000", edit(optimize_section(initial=5000000)), [], "optimize.remesh.initial: expected an integer <="),
    ("sphere_subdivisions", edit(lambda d, t: obj(d)["mesh"].update(subdivisions=14)), [], "scene.objects[0].mesh.subdivisions"),
    ("target_spp", edit(lambda d, t: d.update(optimize={"object": "ball", "target": {"spp": 10 ** 9}})), [],
     "optimize.target.spp"),
    ("garbage_obj", edit(lambda d, t: ((t / "g.obj").write_bytes(b"\x00\x01 not a mesh \xff\xfe"),
                                       obj(d).update(mesh={"file": "g.obj"}))), [],
     "scene.objects[0].mesh.file: cannot read mesh g.obj: not a text OBJ file"),
    ("spp_flag_huge", edit(lambda d, t: None), ["--spp", "99999999999999999999"], "--spp: 99999999999999999999 samples"),
    ("spp_flag_paths", edit(lambda d, t: d["scene"]["film"].update(width=4096, height=4096)), ["--spp", "4096"],
     "--spp: 4096 samples per pixel × 4096×4096"),
    ("spp_flag_zero", edit(lambda d, t: None), ["--spp", "0"], "--spp: expected a positive number"),
]


@pytest.mark.parametrize("make,args,expected", [c[1:] for c in CONFIG_CASES], ids=[c[0] for c in CONFIG_CASES])
def test_bad_input_is_one_line_naming_the_key(tmp_path, write_cfg, capsys, monkeypatch, make, args, expected):
    monkeypatch.chdir(tmp_path)
    cfg = write_cfg(make(tmp_path))
    code, out, err = psdr(capsys, "render", cfg, *args)
    assert_one_line_error(code, out, err, expected)
    if not args:
        assert err[0].startswith(f"error: {cfg}: "), err[0]  # experiment errors name the file
    assert not (tmp_path / "out").exists(), "a failed command must not leave output behind"


GRAD = experiment(parameter={"object": "ball", "kind": "translate"})
USAGE_CASES = [
    ("unknown_flag", ["optimize", "{cfg}", "--bogus"], "psdr optimize: No such option: --bogus"),
    ("spp_not_integer", ["render", "{cfg}", "--spp", "1.5"], "psdr render: Invalid value for '--spp'"),
    ("missing_config", ["render"], "psdr render: Missing argument 'config'"),
    ("misspelt_subcommand", ["rendr", "{cfg}"], "psdr: No such command 'rendr'"),
    ("iterations_zero", ["optimize", "{cfg}", "--iterations", "0"], "--iterations: expected an integer in [1, 1000000], got 0"),
    ("fd_inf", ["grad", "{cfg}", "--fd", "inf"], "--fd: expected a finite number > 0, got inf"),
    ("fd_nan", ["grad", "{cfg}", "--fd", "nan"], "--fd: expected a finite number > 0"),
    ("fd_negative", ["grad", "{cfg}", "--fd", "-0.1"], "--fd: expected a finite number > 0"),
    ("fd_spp_huge", ["grad", "{cfg}", "--fd", "0.01", "--fd-spp", "10000000000"], "--fd-spp: 10000000000 samples"),
    ("views_garbage", ["render", "{cfg}", "--views", "a-b"], "--views: cannot read 'a-b'"),
]


@pytest.mark.parametrize("args,expected", [c[1:] for c in USAGE_CASES], ids=[c[0] for c in USAGE_CASES])
def test_usage_error_is_one_line_with_exit_2(tmp_path, write_cfg, capsys, monkeypatch, args, expected):
    monkeypatch.chdir(tmp_path)
    d = copy.deepcopy(GRAD)
    d["optimize"] = {"object": "ball", "iterations": 2}
    cfg = write_cfg(d)
    code, out, err = psdr(capsys, *[a.format(cfg=cfg) for a in args])
    assert_one_line_error(code, out, err, expected)
    assert not (tmp_path / "out").exists()


def test_help_still_prints_the_usage(capsys):
    code, out, err = psdr(capsys, "render", "--help")
    assert code == 0 and "Usage" in out and not err


def test_usage_error_through_the_real_command_line(tmp_path):
    """``python -m psdr_cli`` passes the exit code on (the console script does the same)."""
    proc = subprocess.run([sys.executable, "-m", "psdr_cli", "render", "--nope"], capture_output=True, text=True,
                          cwd=tmp_path, env=dict(os.environ, COLUMNS="200"), timeout=120)
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert proc.returncode == 2 and len(lines) == 1 and "No such option: --nope" in lines[0], proc.stderr


# --------------------------------------------------------------------------------------------
# Output folders that cannot be written
# --------------------------------------------------------------------------------------------
def test_output_path_that_is_a_file(tmp_path, write_cfg, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "out").write_text("a file, not a folder")
    cfg = write_cfg(experiment(estimator={"spp": 1}))
    code, out, err = psdr(capsys, "render", cfg)
    assert_one_line_error(code, out, err, f"{tmp_path / 'out'}")
    assert "cannot write" in err[0] and "internal error" not in err[0]


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only folders")
def test_read_only_output_folder(tmp_path, write_cfg, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "out").mkdir()
    (tmp_path / "out").chmod(0o500)
    cfg = write_cfg(experiment(estimator={"spp": 1}))
    try:
        code, out, err = psdr(capsys, "render", cfg)
    finally:
        (tmp_path / "out").chmod(0o700)
    assert_one_line_error(code, out, err, "Permission denied")


def test_full_disk_is_named(tmp_path):
    """A write that fails (here: ENOSPC raised by the writer) is a PsdrError naming the file, and
    the final name is never created."""
    target = tmp_path / "image.exr"
    with pytest.raises(PsdrError, match=f"{target}: cannot write \\(No space left on device\\)"):
        with fileio.atomic_path(target):
            raise OSError(28, "No space left on device")
    assert list(tmp_path.iterdir()) == []


def test_non_finite_image_is_not_written(tmp_path):
    target = tmp_path / "view.exr"
    image = np.ones((4, 4, 3))
    image[1, 2, 0] = np.inf
    with pytest.raises(PsdrError, match="view.exr: not written: the image channel R has 1 NaN or infinite"):
        fileio.write_rgb_exr(target, image)
    assert not target.exists()


def test_non_finite_mesh_is_not_written(tmp_path):
    from psdr_cli.run_folder.checkpoints import write_mesh
    V = np.array(TETRA_V, float)
    V[1, 1] = np.nan
    with pytest.raises(PsdrError, match="final.ply: not written: the mesh has 1 NaN or infinite values"):
        write_mesh(tmp_path / "final.ply", V, np.array(TETRA_F))
    assert list(tmp_path.iterdir()) == []


# --------------------------------------------------------------------------------------------
# Run folders: locks, torn logs, damaged states, --resume misuse (one small finished run)
# --------------------------------------------------------------------------------------------
SMALL = {
    "name": "small", "seed": 5,
    "scene": {
        "film": {"width": 8, "height": 8}, "max_depth": 2,
        "cameras": [{"orbit": {"count": 2, "radius": 2.6, "elevation_deg": 20, "target": [0, 0, 0.4], "fov": 30}}],
        "emitters": [{"type": "sky", "sun_direction": [0.5, -0.4, 0.75], "sun_scale": 0.2}],
        "objects": [{"name": "blob", "mesh": {"shape": "sphere", "radius": 0.35, "subdivisions": 2},
                     "transform": {"translate": [0, 0, 0.4], "scale": [1, 0.8, 1.2]},
                     "bsdf": {"type": "diffuse", "reflectance": 0.6}}]},
    "estimator": {"spp": 1, "primary_spp": 1, "boundary_spp": 1, "terms": ["interior", "primary", "direct"]},
    "optimize": {"object": "blob", "target": {"spp": 4}, "iterations": 3, "batch_size": 1,
                 "init": {"mesh": {"shape": "sphere", "radius": 0.3, "subdivisions": 1},
                          "transform": {"translate": [0, 0, 0.4]}},
                 "remesh": {"method": "none"}, "checkpoint_every": 3, "preview_views": [0]},
}


def write_small(folder: Path, data=SMALL) -> Path:
    data = copy.deepcopy(data)
    data["output"] = str(folder / "runs")
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "small.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory):
    """A finished 3-iteration run (copied by each test that changes it)."""
    folder = tmp_path_factory.mktemp("finished")
    cfg = write_small(folder)
    assert cli.run(["optimize", str(cfg)]) == 0
    return folder


@pytest.fixture
def run_copy(finished_run, tmp_path):
    shutil.copytree(finished_run, tmp_path / "copy")
    cfg = write_small(tmp_path / "copy")
    return cfg, tmp_path / "copy" / "runs" / "small"


def iterations_logged(run: Path) -> list:
    with open(run / "log.csv", newline="") as f:
        return [int(r["iteration"]) for r in csv.DictReader(f)]


def test_second_writer_is_refused_with_the_holders_pid(run_copy, capsys):
    cfg, run = run_copy
    with lock_run(RunFiles(run)):
        code, out, err = psdr(capsys, "optimize", cfg, "--resume", "--iterations", "4")
    assert_one_line_error(code, out, err, f"another psdr process (PID {os.getpid()}) is writing this run")
    assert iterations_logged(run) == [0, 1, 2]


def test_a_killed_holder_releases_the_lock(tmp_path):
    lock = tmp_path / ".run.lock"
    holder = subprocess.Popen([sys.executable, "-c", "import fcntl, os, sys, time; f = open(sys.argv[1], 'w'); "
                               "fcntl.flock(f, fcntl.LOCK_EX); print('locked', flush=True); time.sleep(60)", str(lock)],
                              stdout=subprocess.PIPE, text=True)
    assert holder.stdout.readline().strip() == "locked"
    with pytest.raises(PsdrError, match="another psdr process"):
        with lock_run(RunFiles(tmp_path / "run")):
            pass
    holder.kill()
    holder.wait()
    with lock_run(RunFiles(tmp_path / "run")):
        with open(lock, "rb+") as f:
            with pytest.raises(BlockingIOError):
                fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)


def test_two_optimize_processes_on_one_run(tmp_path):
    """Two real `psdr optimize` processes started together: one runs, the other is refused. The run
    asks for 10⁶ iterations, which no machine finishes before the other process has started (150,
    as before, could end first on a fast machine, and the second then found the run finished); the
    refused one exits, then the running one is stopped with a Ctrl-C (it saves and exits 130)."""
    cfg = write_small(tmp_path)
    env = dict(os.environ, COLUMNS="200")
    procs = [subprocess.Popen([sys.executable, "-m", "psdr_cli", "optimize", str(cfg), "--iterations", "1000000"],
                              env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                              preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL)) for _ in range(2)]
    try:
        deadline = time.monotonic() + 600  # a hang guard only
        while all(p.poll() is None for p in procs) and time.monotonic() < deadline:
            time.sleep(0.05)
        refused = next(p for p in procs if p.poll() is not None)
        running = next(p for p in procs if p is not refused)
        assert refused.wait() == 2, refused.communicate()
        assert "is writing this run" in refused.communicate()[1] and running.poll() is None
        while iterations_logged(tmp_path / "runs" / "small") == [] and time.monotonic() < deadline:
            time.sleep(0.05)  # (a Ctrl-C before the first iteration is saved is a plain interrupt)
        running.send_signal(signal.SIGINT)
        _, err = running.communicate(timeout=120)
        assert running.returncode == 130 and "Traceback" not in err, err
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
    done = iterations_logged(tmp_path / "runs" / "small")
    assert done == list(range(len(done))) and len(done) >= 1


TORN_TAILS = {"torn_row": b"3,0", "row_cut_to_number": b"3", "nul_bytes": b"\x00" * 64,
              "garbage_line": b"not,a,row\r\n"}


@pytest.mark.parametrize("tail", list(TORN_TAILS.values()), ids=list(TORN_TAILS))
def test_torn_log_is_read_with_a_warning(run_copy, tail, capsys, tmp_path):
    cfg, run = run_copy
    with open(run / "log.csv", "ab") as f:
        f.write(tail)
    code, out, err = psdr(capsys, "table2", cfg, "--out", tmp_path / "t2.md")
    assert code == 0, err
    assert all(ln.startswith("warning: ") for ln in err) and any("log.csv: line 5" in ln for ln in err), err
    code, out, err = psdr(capsys, "evaluate", cfg, "--samples", "2000")
    assert code == 0 and "internal error" not in "\n".join(err), err


@pytest.mark.parametrize("tail", [TORN_TAILS["torn_row"], TORN_TAILS["nul_bytes"]], ids=["torn_row", "nul_bytes"])
def test_resume_truncates_a_torn_log(run_copy, tail, capsys):
    cfg, run = run_copy
    with open(run / "log.csv", "ab") as f:
        f.write(tail)
    code, out, err = psdr(capsys, "optimize", cfg, "--resume", "--iterations", "4")
    assert code == 0, err
    assert iterations_logged(run) == [0, 1, 2, 3]
    assert len(read_log(run / "log.csv")) == 4


def test_read_log_rejects_a_damaged_middle(tmp_path):
    log = tmp_path / "log.csv"
    log.write_text("iteration,loss,vertices,seconds_guiding,seconds_rendering,seconds_post,seconds_total,skipped,"
                   "guide_bytes\r\n0,0.1,10,0,0.1,0.1,0.2,0,0\r\n1,0.1\r\n2,0.1,10,0,0.1,0.1,0.2,0,0\r\n")
    with pytest.warns(UserWarning, match="line 3 is torn or damaged"):
        assert [r["iteration"] for r in read_log(log)] == ["0"]


def test_state_with_nan_is_refused(run_copy, capsys):
    cfg, run = run_copy
    with np.load(run / "state.npz") as z:
        arrays = {k: z[k] for k in z.files}
    arrays["u"] = arrays["u"].copy()
    arrays["u"][3] = np.nan
    with open(run / "state.npz", "wb") as f:
        np.savez(f, **arrays)
    final = (run / "final.ply").read_bytes()
    code, out, err = psdr(capsys, "optimize", cfg, "--resume", "--iterations", "4")
    assert_one_line_error(code, out, err, "state.npz: the saved state holds NaN or infinite values")
    assert (run / "final.ply").read_bytes() == final


def test_resume_with_fewer_iterations_is_refused(run_copy, capsys):
    cfg, run = run_copy
    code, out, err = psdr(capsys, "optimize", cfg, "--resume", "--iterations", "2")
    assert_one_line_error(code, out, err, "--iterations: 2 is fewer than the 3 iterations the run")


def test_resume_after_an_edit_keeps_the_old_run(run_copy, capsys):
    cfg, run = run_copy
    data = yaml.safe_load(cfg.read_text())
    data["optimize"]["learning_rate"] = 0.02
    cfg.write_text(yaml.safe_dump(data))
    code, out, err = psdr(capsys, "optimize", cfg, "--resume")
    assert code == 0, err
    kept = list(run.parent.glob("small.previous-*"))
    assert len(kept) == 1 and (kept[0] / "final.ply").exists() and iterations_logged(kept[0]) == [0, 1, 2]
    said = "".join(err)  # the warnings say where the old run went (wrapped on a terminal)
    assert "changed since" in said and f"kept in {kept[0]}" in said, err


# --------------------------------------------------------------------------------------------
# Reproducibility
# --------------------------------------------------------------------------------------------
GUIDED = copy.deepcopy(SMALL)
GUIDED["estimator"].update(guiding="grid", grid={"resolution": [16, 4, 4], "samples_per_cell": 16})
GUIDED["optimize"].update(iterations=6, guide_every=3, albedo={"init": [0.3, 0.4, 0.5]})
#: Kd-tree guides of the direct term fitted to the loop's own samples (at 3 and 6), 64 samples per
#: pixel, the blob's shadow on a floor (the direct term's signal)
LOOP_FED = copy.deepcopy(GUIDED)
LOOP_FED["estimator"].update(guiding="kdtree", boundary_spp=64, edge_sort=True)
LOOP_FED["estimator"].pop("grid")
LOOP_FED["scene"]["objects"].append({"name": "floor", "mesh": {"shape": "plane", "size": 4},
                                     "bsdf": {"type": "diffuse", "reflectance": 0.5}, "edges": False})
LOOP_FED["optimize"].update(iterations=8)


@pytest.mark.slow
@bit_reproducible
@pytest.mark.parametrize("data", [GUIDED, LOOP_FED], ids=["grid", "loop-fed kdtree"])
def test_stopped_and_resumed_guided_run_reproduces_the_uninterrupted_one(tmp_path, capsys, data):
    """Guided (grid guides built every 3 iterations, or Kd-trees fitted every 3 iterations to the
    samples the loop kept) with RGB albedo: a run stopped after iteration 4 (between two guide
    refreshes) and resumed gives the uninterrupted run's losses exactly; the guides (and the
    samples kept since the last fit) are restored, not rebuilt at the resume iteration."""
    full = write_small(tmp_path / "full", data)
    assert cli.run(["optimize", str(full)]) == 0
    part = write_small(tmp_path / "part", data)
    assert cli.run(["optimize", str(part), "--iterations", "4"]) == 0
    assert cli.run(["optimize", str(part), "--resume"]) == 0

    def losses(folder):
        return [r["loss"] for r in read_log(folder / "runs" / "small" / "log.csv")]
    assert losses(tmp_path / "part") == losses(tmp_path / "full")
    a = (tmp_path / "full" / "runs" / "small" / "final.ply").read_bytes()
    assert (tmp_path / "part" / "runs" / "small" / "final.ply").read_bytes() == a


def test_loop_fed_guides_are_fitted_when_a_batch_traces_its_views_together(tmp_path):
    """With two views per batch the unguided terms trace the batch as one wavefront; the loop-fed
    direct term must still run its passes view by view while its sample log is empty (before the
    first fit), keep their samples and fit its Kd-trees at the first refresh: the log reports no
    guide memory before iteration 3 and some from there on. (An empty log once counted as no
    guide, so the term was batched, kept nothing and stayed unguided for the whole run.)"""
    data = copy.deepcopy(LOOP_FED)
    data["optimize"].update(iterations=5, batch_size=2)
    data["optimize"].pop("albedo")
    run = write_small(tmp_path, data)
    assert cli.run(["optimize", str(run)]) == 0
    rows = read_log(tmp_path / "runs" / "small" / "log.csv")
    memory = [float(r["guide_bytes"]) for r in rows]
    assert memory[:3] == [0, 0, 0] and all(m > 0 for m in memory[3:]), memory


def test_taking_the_lock_clears_a_killed_writers_temporaries(tmp_path):
    """kill -9 between an atomic write's temporary and its rename leaves ``.<stem>.<random>.tmp<ext>``;
    the next holder of the run's lock deletes it and keeps every named file."""
    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    (run / "state.npz").write_bytes(b"kept")
    left = [run / ".state.k3j9.tmp.npz", run / "checkpoints" / ".iter_0004.x1y2.tmp.ply"]
    for path in left:
        path.write_bytes(b"partial")
    with lock_run(RunFiles(run)):
        assert not any(path.exists() for path in left)
    assert (run / "state.npz").read_bytes() == b"kept"
