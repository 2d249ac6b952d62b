"""Shared helpers: experiment files written into a temporary folder, and CLI runs."""
import copy
import gc
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import OpenEXR
import pytest
import yaml

import psdr_cli  # noqa: F401  (prepares Dr.Jit before any test imports it)
from psdr_cli.support import backend, llvm_target
import mitsuba as mi

#: Mitsuba's log level in a new process (tests may lower it; run_psdr restores it per call)
MITSUBA_LOG_LEVEL = mi.log_level()

# One Dr.Jit thread in the optimisation loop, in this process and the psdr processes tests start:
# the checks that runs are bit-reproducible (resume, recorded against traced) hold with one thread
# only, and a user's PSDR_OPTIMIZE_THREADS (docs/optimize.md) would turn them red.
os.environ["PSDR_OPTIMIZE_THREADS"] = "1"


def suite_runs_on_cuda() -> bool:
    """True when the tests run on a CUDA variant (``PSDR_VARIANT``, or ``auto`` with a GPU)."""
    variant = os.environ.get("PSDR_VARIANT") or "auto"
    return variant.startswith("cuda") or (variant == "auto" and backend.cuda_available())


#: For checks that two runs are bit-identical (a resumed run and the uninterrupted one, a pass
#: batched and alone). They hold on the LLVM backend with one thread; on CUDA, Dr.Jit's atomic
#: scatter-adds accumulate in scheduling order, so runs agree only to the last bits
#: (docs/optimize.md, "Reproducibility"), and six such checks failed on the first GPU run.
bit_reproducible = pytest.mark.skipif(
    suite_runs_on_cuda(), reason="CUDA's atomic scatter-adds are not bit-reproducible (docs/optimize.md)")

REPO = Path(__file__).resolve().parents[1]


def suite_lanes() -> int | None:
    """The SIMD lanes the suite's LLVM kernels run with: ``PSDR_LLVM_LANES`` (4, 8 or 16; psdr_cli
    applies it at import, in this process and in every ``psdr`` process a test starts, which
    inherits the variable), None for the host's own target (docs/testing.md, "Vector widths")."""
    try:
        return llvm_target.requested_lanes()
    except ValueError as exc:
        raise pytest.UsageError(str(exc)) from None


def pytest_configure(config):
    """A suite asked to run at a vector width runs at it, or not at all."""
    lanes = suite_lanes()
    if lanes is not None and llvm_target.current_target()[1] != lanes:
        raise pytest.UsageError(backend.lanes_reason() or f"PSDR_LLVM_LANES={lanes}: Dr.Jit compiles for "
                                                          f"{llvm_target.current_target()}")


def pytest_report_header(config):
    cpu, width = llvm_target.current_target()
    source = "PSDR_LLVM_LANES" if suite_lanes() is not None else "the host's own"
    return f"Dr.Jit LLVM target: {cpu}, {width} lanes ({source})"

#: A small valid experiment: diffuse sphere on a floor under an area light, one camera.
BASE = {
    "name": "t",
    "output": "out",
    "seed": 1,
    "scene": {
        "film": {"width": 24, "height": 16},
        "max_depth": 2,
        "cameras": [{"origin": [0, -3, 2], "target": [0, 0, 0.3], "fov": 40}],
        "emitters": [{"type": "area", "center": [0, 0, 2.5], "normal": [0, 0, -1], "size": [1, 1],
                      "radiance": 10}],
        "objects": [
            {"name": "ball", "mesh": {"shape": "sphere", "radius": 0.4, "subdivisions": 2},
             "transform": {"translate": [0, 0, 0.5]},
             "bsdf": {"type": "diffuse", "reflectance": [0.7, 0.5, 0.3]}},
            {"name": "floor", "mesh": {"shape": "plane", "size": 4}, "edges": False},
        ],
    },
    "estimator": {"spp": 4},
}


def experiment(**overrides):
    """A deep copy of BASE with top-level keys replaced."""
    d = copy.deepcopy(BASE)
    d.update(overrides)
    return d


@pytest.fixture
def write_cfg(tmp_path):
    """write_cfg(dict_or_text, name='exp.yaml') -> path of the written experiment file."""
    def write(data, name="exp.yaml"):
        path = tmp_path / name
        path.write_text(data if isinstance(data, str) else yaml.safe_dump(data, sort_keys=False))
        return path
    return write


def run_cli(*args, cwd=None, timeout=600):
    """Run ``python -m psdr_cli ARGS``; returns the CompletedProcess (text output)."""
    env = dict(os.environ, PYTHONUNBUFFERED="1", COLUMNS="200")
    env.pop("PSDR_DEBUG", None)
    return subprocess.run([sys.executable, "-m", "psdr_cli", *map(str, args)], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=timeout)


def psdr_exit_code(argv, cwd=None) -> int:
    """The exit code of ``psdr ARGV`` run in this process through the function ``python -m
    psdr_cli`` calls (``psdr_cli.cli.run``), as a new process would see it: 200 columns,
    PSDR_DEBUG unset, Mitsuba's log level of a new process, warnings filtered afresh (a warning
    shown once per process shows in every call) and psdr's warning hook undone afterwards, the
    working directory ``cwd``; all restored after the call. The caller captures the output."""
    import warnings
    from psdr_cli import cli
    widths = cli.console._width, cli.out._width  # rich sets these from COLUMNS at import
    debug = os.environ.pop("PSDR_DEBUG", None)
    here, level = os.getcwd(), mi.log_level()
    try:
        cli.console.width = cli.out.width = 200
        mi.set_log_level(MITSUBA_LOG_LEVEL)
        os.chdir(cwd or here)
        with warnings.catch_warnings():
            try:
                return cli.run([str(a) for a in argv])
            except SystemExit as exc:  # as the interpreter turns sys.exit into an exit status
                return exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    finally:
        os.chdir(here)
        mi.set_log_level(level)
        cli.console._width, cli.out._width = widths
        if debug is not None:
            os.environ["PSDR_DEBUG"] = debug


@pytest.fixture
def run_psdr(capfd):
    """run_psdr(*args, cwd=None) -> CompletedProcess: ``psdr ARGS`` run in this process
    (:func:`psdr_exit_code`), for checks that are not about the process itself (exit codes and
    one-line errors, run folders): it saves the ~4 s of imports a ``run_cli`` subprocess costs.
    As ``run_cli``: the exit code, and stdout and stderr captured at the file descriptors (C++
    output included). Keep ``run_cli`` for what only a real process shows: kills, signals, hangs,
    locks held by another process, the entry point itself."""
    def run(*args, cwd=None):
        capfd.readouterr()
        code = psdr_exit_code(args, cwd)
        captured = capfd.readouterr()
        return subprocess.CompletedProcess(["psdr", *map(str, args)], code, captured.out, captured.err)
    return run


@pytest.fixture(autouse=True)
def freed_mitsuba_objects():
    """Every test starts after a garbage collection. Mitsuba registers each BSDF, emitter and
    shape with Dr.Jit, and kernels that dispatch over them (a BSDF evaluated at a ray's hit) hold
    the instances' registry ids; an id is reused once its object is freed. Earlier tests' scenes
    left in reference cycles were freed only at some later collection, so a test's kernels
    depended on what its worker had run before, and every suite run compiled several hundred
    kernels again (docs/testing.md, "Stop 50")."""
    gc.collect()
    yield


# --------------------------------------------------------------------------------------------
# Parallel runs (pytest-xdist, `make test` runs `-n auto --dist loadgroup`)
# --------------------------------------------------------------------------------------------
def shared_fixtures(item) -> list:
    """Names of the module-scoped fixtures ``item`` requests: tests that share one run in one
    worker, or each worker would build it again."""
    defs = getattr(item, "_fixtureinfo", None)
    if defs is None:
        return []
    return sorted(name for name, fixture_defs in defs.name2fixturedefs.items()
                  if fixture_defs[-1].scope == "module")


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(config, items):
    """Group the tests of a module that request a module-scoped fixture (one ``xdist_group`` per
    module, so that no fixture is built twice, whichever tests share it), and run the groups
    and tests that hold a ``slow`` test first, so that no long check starts last and keeps
    one worker busy alone at the end (the order is only a schedule: every test still runs)."""
    groups = {}
    for item in items:
        if shared_fixtures(item):
            group = item.module.__name__
            item.add_marker(pytest.mark.xdist_group(group))
            groups.setdefault(group, []).append(item)
    slow_groups = {g for g, members in groups.items() if any(m.get_closest_marker("slow") for m in members)}

    def starts_late(item):
        marks = [m.args[0] if m.args else m.kwargs.get("name") for m in item.iter_markers("xdist_group")]
        return not (item.get_closest_marker("slow") or slow_groups.intersection(marks))

    items.sort(key=starts_late)


def write_raw_exr(path, rgb):
    """An RGB EXR of ``rgb`` (H, W, 3) written as given, NaN included (psdr's own writers refuse
    non-finite images). OpenEXR, not ``mi.Bitmap.write``: that waits on Dr.Jit's thread pool and
    hangs when the process has one CPU (one Dr.Jit thread)."""
    OpenEXR.File({}, {"RGB": np.ascontiguousarray(rgb, np.float32)}).write(str(path))
