"""Run fingerprints: a key added with its default changes none, and run folders whose run.json
holds a version-1 fingerprint (no ``fingerprint_version``) are still resumed."""
import copy
import csv
import json
import re
import shutil
from dataclasses import field, make_dataclass, replace

import pytest

from conftest import REPO
from psdr_cli.commands.optimize import optimize
from psdr_cli.errors import ConfigError
from psdr_cli.experiment.load import load_experiment, parse_experiment
from psdr_cli.run_folder.fingerprint import run_fingerprint
from psdr_cli.run_folder.fingerprint_v1 import fingerprint_v1
from psdr_cli.run_folder.variant_folders import variant_experiments
from test_optimize import TINY, write

#: A run written by psdr with version-1 fingerprints: tiny.yaml, 2 iterations (run.json, state, log, targets).
SAVED_V1 = REPO / "tests" / "data" / "resume_v1"


def tiny_cases():
    """{name: experiment data}: TINY and variants that set engine, stage and guide keys."""
    mitsuba = copy.deepcopy(TINY)
    mitsuba["estimator"] = {"engine": "mitsuba", "mitsuba_spp": 4, "primary_sampling": "jump"}
    staged = copy.deepcopy(TINY)
    staged["estimator"].update(guiding="kdtree", primary_sampling="jump", kdtree={"initial_samples": 4096})
    staged["optimize"].update({"lambda": [30, 10], "downsample": [2, 1], "learning_rate": 0.02})
    single = copy.deepcopy(TINY)
    single["optimize"]["lambda"] = 30
    return {"tiny": copy.deepcopy(TINY), "mitsuba": mitsuba, "staged": staged, "lambda": single}


def with_new_key(config, default=7):
    """A copy of a config dataclass instance whose class has one more field, ``new_key``, set to
    ``default`` (a subclass of the same name, as if the key had been added to config.py)."""
    cls = make_dataclass(type(config).__name__, [("new_key", int, field(default=default))], bases=(type(config),))
    return cls(**{f: getattr(config, f) for f in config.__dataclass_fields__})


def test_fingerprints_of_both_versions_are_unchanged(tmp_path):
    """The version-1 values were written by the release that introduced them (its run.json files
    must still resume); the version-2 values pin today's fingerprints."""
    v1 = {"tiny": "d576a7a191fe311d", "mitsuba": "29107c6ca5c19686", "staged": "f5134c9678762de6",
          "lambda": "7fdae8034ecf8cb5"}
    v2 = {"tiny": "50f91c45b863fcc9", "mitsuba": "1562ecac51c7428f", "staged": "965a7a9214c602fe",
          "lambda": "b07c5439a8d601b5"}
    for name, data in tiny_cases().items():
        exp = parse_experiment(data, tmp_path / f"{name}.yaml", cwd=tmp_path)
        assert (fingerprint_v1(exp), run_fingerprint(exp)) == (v1[name], v2[name]), name


def test_a_new_key_at_its_default_changes_no_fingerprint(tmp_path):
    """Adding a key (top level or nested) with its default leaves both versions' fingerprints
    as they were; the key set to another value changes them."""
    for name, data in tiny_cases().items():
        exp = parse_experiment(data, tmp_path / f"{name}.yaml", cwd=tmp_path)
        before = (fingerprint_v1(exp), run_fingerprint(exp))
        changed = [replace(exp, estimator=with_new_key(exp.estimator)),
                   replace(exp, estimator=replace(exp.estimator, kdtree=with_new_key(exp.estimator.kdtree))),
                   replace(exp, optimize=with_new_key(exp.optimize)),
                   replace(exp, scene=with_new_key(exp.scene))]
        for new in changed:
            assert (fingerprint_v1(new), run_fingerprint(new)) == before, name
        other = replace(exp, optimize=replace(with_new_key(exp.optimize), new_key=8))
        assert fingerprint_v1(other) != before[0] and run_fingerprint(other) != before[1], name


def log_losses(run):
    with open(run / "log.csv", newline="") as f:
        return [row["loss"] for row in csv.DictReader(f)]


def test_a_run_with_a_version_1_fingerprint_resumes(tmp_path, run_psdr):
    """The saved run continues (resumed from 2, its log kept) and gets a version-2 run.json; the
    same run under a changed experiment starts afresh."""
    shutil.copytree(SAVED_V1, tmp_path / "a")
    run = tmp_path / "a" / "output" / "tiny"
    assert "fingerprint_version" not in json.loads((run / "run.json").read_text())
    saved = log_losses(run)
    r = run_psdr("optimize", "tiny.yaml", "--resume", "--iterations", "3", cwd=tmp_path / "a")  # output: output
    out = (r.stdout + r.stderr).replace("\n", " ")
    assert r.returncode == 0 and "changed" not in out and "resumed from 2" in out, out
    losses = log_losses(run)
    assert len(losses) == 3 and losses[:2] == saved
    record = json.loads((run / "run.json").read_text())
    exp = parse_experiment(copy.deepcopy(TINY), tmp_path / "x.yaml", cwd=tmp_path)  # the keys of tiny.yaml
    assert record["fingerprint_version"] == 2 and len(record["fingerprint"]) == 16
    assert record["fingerprint"] != fingerprint_v1(exp)
    shutil.copytree(SAVED_V1, tmp_path / "b")
    cfg = tmp_path / "b" / "tiny.yaml"
    cfg.write_text(cfg.read_text().replace("batch_size: 1", "batch_size: 2"))
    r = run_psdr("optimize", cfg, "--resume", "--iterations", "3", cwd=tmp_path / "b")
    out = (r.stdout + r.stderr).replace("\n", " ")
    assert r.returncode == 0 and "changed since" in out and "resumed from 0" in out, out


def test_a_variant_with_its_own_step_is_a_run_with_that_step(tmp_path):
    """``optimize.variants`` entries may set ``learning_rate`` and ``lambda`` (a step-size sweep
    per estimator): the variant's run has them and the fingerprint of the same experiment written
    with that step, and a variant without them keeps the experiment's."""
    stepped = copy.deepcopy(TINY)
    stepped["optimize"].update({"learning_rate": 0.3, "lambda": [7, 3]})   # TINY remeshes once: 2 stages
    data = copy.deepcopy(TINY)
    data["optimize"]["variants"] = [{"label": "plain"}, {"label": "step", "learning_rate": 0.3, "lambda": [7, 3]}]
    exp = parse_experiment(data, tmp_path / "tiny.yaml", cwd=tmp_path)
    (_, plain), (_, step) = variant_experiments(exp)
    assert plain.optimize.learning_rate == exp.optimize.learning_rate and plain.optimize.lambda_ == exp.optimize.lambda_
    assert step.optimize.learning_rate == 0.3 and step.optimize.lambda_ == (7.0, 3.0)
    alone = parse_experiment(stepped, tmp_path / "tiny.yaml", cwd=tmp_path)
    alone = replace(alone, optimize=replace(alone.optimize, target_seed=alone.seed))   # as every variant's
    assert run_fingerprint(step) == run_fingerprint(alone) != run_fingerprint(plain)


def test_a_variant_step_out_of_range_names_its_key(tmp_path):
    for bad, needle in (({"learning_rate": 0}, "learning_rate"), ({"lambda": -1}, "lambda"),
                        ({"lambda": [1, 2, 3, 4, 5]}, "lambda")):
        data = copy.deepcopy(TINY)
        data["optimize"]["variants"] = [{"label": "v", **bad}]
        with pytest.raises(ConfigError, match=re.escape(f"optimize.variants[0].{needle}")):
            parse_experiment(data, tmp_path / "tiny.yaml", cwd=tmp_path)


def test_variant_labels_that_are_psdrs_own_folders_are_refused(tmp_path):
    """A variant's run folder is <output>/<name>/<label>: a label naming a command's folder
    (render, grad, compare, guide_stats) or a run's own entries would share it."""
    for label in ("render", "grad", "compare", "guide_stats", "targets", "checkpoints"):
        data = copy.deepcopy(TINY)
        data["optimize"]["variants"] = [{"label": label}]
        with pytest.raises(ConfigError, match=re.escape(f"optimize.variants[0].label: '{label}' is taken")):
            parse_experiment(data, tmp_path / "tiny.yaml", cwd=tmp_path)


def kept_runs(run):
    return sorted(run.parent.glob(f"{run.name}.previous-*"))


def test_a_fresh_run_of_a_changed_target_keeps_the_old_runs_reference_and_targets(tmp_path):
    """The previous run is moved aside before anything of the new run is written: its
    reference.ply and targets stay those it was fitted to (they were overwritten by the new
    target's before the move), and the commands' own output folders stay where they are."""
    data = copy.deepcopy(TINY)
    data["optimize"].update(iterations=1, remesh={"method": "none"})
    exp = load_experiment(write(tmp_path, data))
    optimize(exp, warn=lambda m: None)
    run = exp.run_dir
    (run / "render").mkdir()
    (run / "render" / "view_000.exr").write_bytes(b"a render of psdr render")
    reference = (run / "reference.ply").read_bytes()
    target = (run / "targets" / "view_000.exr").read_bytes()
    data["scene"]["objects"][0]["mesh"]["size"] = 0.6
    optimize(load_experiment(write(tmp_path, data)), warn=lambda m: None)
    [kept] = kept_runs(run)
    assert (kept / "reference.ply").read_bytes() == reference and (run / "reference.ply").read_bytes() != reference
    assert (kept / "targets" / "view_000.exr").read_bytes() == target
    assert (run / "render" / "view_000.exr").read_bytes() == b"a render of psdr render"
    assert not (kept / "render").exists() and (kept / "log.csv").exists()


def test_a_changed_experiment_with_a_bad_input_moves_nothing(tmp_path, run_psdr):
    """--resume after an edit that also breaks an input: one line, and the old run is neither
    moved nor touched (the move happened before the inputs were read)."""
    data = copy.deepcopy(TINY)
    data["optimize"].update(iterations=1, remesh={"method": "none"})
    cfg = write(tmp_path, data)
    exp = load_experiment(cfg)
    optimize(exp, warn=lambda m: None)
    before = {p.relative_to(exp.run_dir): p.read_bytes() for p in exp.run_dir.rglob("*") if p.is_file()}
    data["optimize"]["target"] = {"images": "no_such_folder/*.exr"}   # found missing only when read
    r = run_psdr("optimize", write(tmp_path, data), "--resume")
    assert r.returncode == 2 and "optimize.target.images: no file matches" in r.stderr, r.stderr
    assert not kept_runs(exp.run_dir)
    assert {p.relative_to(exp.run_dir): p.read_bytes() for p in exp.run_dir.rglob("*") if p.is_file()} == before
