"""Start-up: libLLVM discovery, kernel cache folder, variant choice, CLI entry point."""
import os

import pytest

from psdr_cli.errors import PsdrError
from psdr_cli.support import backend

from conftest import experiment, run_cli


@pytest.mark.parametrize("name, major", [("/usr/lib/x86_64-linux-gnu/libLLVM-19.so", 19),
                                         ("/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1", 19),
                                         ("/usr/lib/llvm-17/lib/libLLVM.so", 17),
                                         ("/usr/lib/x86_64-linux-gnu/libLLVM-15.so.1", 15)])
def test_llvm_major_from_file_name(name, major):
    assert backend._llvm_major(name) == major


def test_import_selected_a_supported_libllvm_and_a_stable_cache():
    path = os.environ.get("DRJIT_LIBLLVM_PATH")
    assert path, "DRJIT_LIBLLVM_PATH unset: psdr found no libLLVM >= 16, or removed an unusable one"
    assert os.path.exists(path) and backend._llvm_major(path) >= backend.MIN_LLVM
    assert os.path.isdir(os.environ["DRJIT_CACHE_DIR"])
    found = backend.find_libllvm()
    assert found is not None and backend._llvm_major(found) >= 16


def test_auto_variant_is_llvm_without_cuda():
    expected = "cuda_ad_rgb" if backend.cuda_available() else "llvm_ad_rgb"
    assert backend.select_variant("auto") == expected


def test_bad_variant_override(monkeypatch):
    monkeypatch.setenv("PSDR_VARIANT", "scalar_spectral")
    with pytest.raises(PsdrError, match="unknown variant 'scalar_spectral'"):
        backend.select_variant("auto")


@pytest.mark.parametrize("name, expected", [
    ("libLLVM-15.so", "is LLVM 15"),              # an existing file of an old LLVM
    ("missing/libLLVM-19.so", "does not exist"),  # a path to nothing (Dr.Jit printed its own loader errors)
])
def test_unusable_llvm_is_refused_in_one_line_with_the_package_to_install(tmp_path, write_cfg, monkeypatch,
                                                                          name, expected):
    lib = tmp_path / name
    if "missing" not in name:
        lib.write_bytes(b"")
    monkeypatch.setenv("DRJIT_LIBLLVM_PATH", str(lib))
    monkeypatch.setenv("PSDR_VARIANT", "llvm_ad_rgb")
    proc = run_cli("render", write_cfg(experiment()), cwd=tmp_path)
    assert proc.returncode == 2
    assert expected in proc.stderr and "apt-get install libllvm19" in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1 and "Traceback" not in proc.stderr, proc.stderr


def test_a_bare_library_name_is_left_to_the_system_search_and_an_empty_path_is_unset(monkeypatch):
    """``DRJIT_LIBLLVM_PATH=libLLVM.so.19.1`` (no folder) is what Dr.Jit loads through the library
    search path: kept; one naming an old LLVM is refused; an empty value gets psdr's search."""
    assert backend.unusable_llvm_reason("libLLVM.so.19.1") is None
    assert "is LLVM 15" in backend.unusable_llvm_reason("libLLVM-15.so")
    monkeypatch.setattr(backend, "_unusable_llvm", None)
    monkeypatch.setenv("DRJIT_LIBLLVM_PATH", "libLLVM.so.19.1")
    backend.configure_environment()
    assert os.environ["DRJIT_LIBLLVM_PATH"] == "libLLVM.so.19.1" and backend._unusable_llvm is None
    monkeypatch.setenv("DRJIT_LIBLLVM_PATH", "")
    backend.configure_environment()
    assert os.environ.get("DRJIT_LIBLLVM_PATH") == backend.find_libllvm() and backend._unusable_llvm is None


# The next three run psdr in this process (run_psdr: the messages and exit codes are the point);
# the real entry point: test_unusable_llvm_* above, tests/test_faults.py::
# test_usage_error_through_the_real_command_line and test_bad_inputs.py's REAL_PROCESS cases.
def test_no_arguments_prints_help_with_every_subcommand(run_psdr):
    proc = run_psdr()
    assert proc.returncode == 0
    for cmd in ("render", "grad", "guide-stats", "optimize", "evaluate"):
        assert cmd in proc.stdout


def test_optimize_without_its_section_is_a_one_line_error(tmp_path, write_cfg, run_psdr):
    proc = run_psdr("optimize", write_cfg(experiment()), cwd=tmp_path)
    assert proc.returncode == 2 and "optimize: missing" in proc.stderr and "Traceback" not in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1


def test_grad_without_parameter_is_a_one_line_error(tmp_path, write_cfg, run_psdr):
    proc = run_psdr("grad", write_cfg(experiment()), cwd=tmp_path)
    assert proc.returncode == 2 and "parameter: missing" in proc.stderr and "Traceback" not in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1 and not (tmp_path / "runs").exists()


def test_a_vector_width_is_applied_in_a_new_process_and_changes_the_rounding(tmp_path):
    """PSDR_LLVM_LANES sets Dr.Jit's LLVM target at import, for every kernel of the process: the
    target reads back, and 1/√x rounds as that target rounds (with 16 lanes from AVX-512's
    vrsqrt14, with 8 lanes from AVX's vrsqrtps: the two disagree in the last bits). Each width's
    kernels include a fused multiply-add (4 lanes without FMA made LLVM call fmaf, and Dr.Jit
    aborted). The kernels go to psdr's cache folder (applying the width imports Dr.Jit, which reads
    the folder then: it went to Dr.Jit's own default when the width was applied first)."""
    import subprocess
    import sys
    from psdr_cli.support import llvm_target
    code = ("import psdr_cli; from psdr_cli.support import backend, llvm_target; backend.select_variant('llvm_ad_rgb'); "
            "import drjit as dr, mitsuba as mi, numpy as np; x = dr.fma(dr.arange(mi.Float, 4096), 0.37, 1.0); "
            "print(llvm_target.current_target()[1], np.asarray(dr.rsqrt(x)).tobytes().hex())")
    flags = llvm_target.cpu_flags()
    out = {}
    for lanes, (cpu, _, flag) in llvm_target.TARGETS.items():
        if flag not in flags:
            continue
        env = dict(os.environ, PSDR_LLVM_LANES=str(lanes), XDG_CACHE_HOME=str(tmp_path / str(lanes)))
        env.pop("DRJIT_CACHE_DIR", None)
        r = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
        assert r.returncode == 0, r.stderr
        assert list((tmp_path / str(lanes) / "psdr" / "drjit").glob("*.llvm.*")), lanes
        width, values = r.stdout.split()
        assert int(width) == lanes
        out[lanes] = values
    assert out or "avx2" not in flags  # (4 and 8 lanes are AVX2 code: llvm_target.TARGETS)
    if 16 in out and 8 in out:
        assert out[16] != out[8]


def test_a_bad_or_unreachable_vector_width_is_one_line(monkeypatch, tmp_path, write_cfg):
    from psdr_cli.support import llvm_target
    monkeypatch.setenv("PSDR_LLVM_LANES", "12")
    with pytest.raises(ValueError, match="PSDR_LLVM_LANES: expected one of 4, 8, 16"):
        llvm_target.requested_lanes()
    monkeypatch.setattr(llvm_target, "cpu_flags", lambda: {"sse2"})
    assert "this CPU has no AVX512F" in llvm_target.force_lanes(16)
    # a new process: one line, exit 2, nothing rendered
    r = run_cli("render", write_cfg(experiment()), "--out", tmp_path / "r", cwd=tmp_path)
    assert r.returncode == 2 and r.stderr.strip().splitlines() == [
        "error: PSDR_LLVM_LANES: expected one of 4, 8, 16 (SIMD lanes of Dr.Jit's CPU kernels) or unset, got '12'"]
    assert not (tmp_path / "r").exists()
