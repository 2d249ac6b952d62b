"""Owns Dr.Jit / Mitsuba start-up: libLLVM discovery, the kernel cache, variant selection and
Dr.Jit's CPU thread count. Reads the environment (``DRJIT_*``, ``PSDR_*``, ``XDG_CACHE_HOME``);
writes ``DRJIT_LIBLLVM_PATH``, ``DRJIT_CACHE_DIR``, the cache folder and Mitsuba's variant.

Dr.Jit's LLVM backend needs libLLVM >= 16 (LLVM 15 aborts with "Cannot select: fminimum").
The library is chosen through the ``DRJIT_LIBLLVM_PATH`` environment variable, which must be set
before ``drjit`` is first imported. :func:`configure_environment` does that and runs when
``psdr_cli`` is imported, so every entry point (CLI, Python API, tests) gets the same set-up.
"""
from __future__ import annotations

import glob
import os
import re
import subprocess
from contextlib import contextmanager

from . import llvm_target
from ..config.vocabularies import VARIANTS
from ..errors import PsdrError

#: Oldest LLVM major version Dr.Jit's LLVM backend works with.
MIN_LLVM = 16
#: Debian/Ubuntu package that provides a suitable libLLVM.
LLVM_PACKAGE = "libllvm19"

_SEARCH_GLOBS = (
    "/usr/lib/x86_64-linux-gnu/libLLVM*.so*",
    "/usr/lib/aarch64-linux-gnu/libLLVM*.so*",
    "/usr/lib/llvm-*/lib/libLLVM*.so*",
    "/usr/lib64/libLLVM*.so*",
    "/usr/lib/libLLVM*.so*",
    "/usr/local/lib/libLLVM*.so*",
    "/opt/homebrew/opt/llvm/lib/libLLVM.dylib",
    "/usr/local/opt/llvm/lib/libLLVM.dylib",
)
_VERSION_RE = re.compile(r"libLLVM(?:-(\d+)|\.so\.(\d+))")


def _llvm_major(path: str) -> int | None:
    """Major version encoded in a libLLVM file name (``libLLVM-19.so``, ``libLLVM.so.19.1``)."""
    m = _VERSION_RE.search(os.path.basename(path))
    if m:
        return int(m.group(1) or m.group(2))
    m = re.search(r"llvm-(\d+)", path)
    return int(m.group(1)) if m else None


def find_libllvm(min_version: int = MIN_LLVM) -> str | None:
    """Path of the newest libLLVM with major version >= ``min_version``, or None."""
    candidates = set()
    for pattern in _SEARCH_GLOBS:
        candidates.update(glob.glob(pattern))
    try:
        out = subprocess.run(["ldconfig", "-p"], capture_output=True, text=True, timeout=10).stdout
        candidates.update(re.findall(r"=> (\S*libLLVM\S*)", out))
    except (OSError, subprocess.SubprocessError):
        pass
    found = []
    for path in candidates:
        major = _llvm_major(path)
        if major is not None and major >= min_version and os.path.exists(path):
            found.append((major, len(path), path))
    return max(found)[2] if found else None


def cache_root() -> str:
    """psdr's folder of on-disk caches: ``$XDG_CACHE_HOME/psdr`` when that is an absolute path
    (the XDG rule: a relative one is ignored), else ``~/.cache/psdr``."""
    base = os.environ.get("XDG_CACHE_HOME", "")
    if not os.path.isabs(base):
        base = os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "psdr")


def default_cache_dir() -> str:
    """Stable folder for Dr.Jit's on-disk kernel cache."""
    return os.path.join(cache_root(), "drjit")


#: Why the user's ``DRJIT_LIBLLVM_PATH`` cannot be used (set by :func:`configure_environment`,
#: reported by :func:`select_variant` when an LLVM variant is asked for), or None.
_unusable_llvm: str | None = None
#: Why PSDR_LLVM_LANES cannot be applied (reported when an LLVM variant is selected), or None.
_unusable_lanes: str | None = None


def unusable_llvm_reason(path: str) -> str | None:
    """Why Dr.Jit's LLVM backend cannot load ``path``: a path (with a directory) to nothing, or a
    file name that says an LLVM older than ``MIN_LLVM``; None when it looks usable (a bare name
    such as ``libLLVM.so.19.1`` is left to the system's library search, as Dr.Jit does)."""
    if os.sep in path and not os.path.exists(path):
        return (f"DRJIT_LIBLLVM_PATH={path} does not exist; point it at a libLLVM >= {MIN_LLVM} "
                f"or unset it (install one with 'apt-get install {LLVM_PACKAGE}')")
    major = _llvm_major(path)
    if major is not None and major < MIN_LLVM:
        return (f"DRJIT_LIBLLVM_PATH={path} is LLVM {major}; Dr.Jit needs LLVM >= {MIN_LLVM} "
                f"(install it with 'apt-get install {LLVM_PACKAGE}' and unset DRJIT_LIBLLVM_PATH)")
    return None


def configure_environment() -> None:
    """Set ``DRJIT_LIBLLVM_PATH`` and ``DRJIT_CACHE_DIR`` unless the user already did.

    Best run before the first ``import drjit``. Dr.Jit reads the variables when a backend is first
    initialised, so setting them after the import still works as long as no LLVM kernel ran yet.
    A user's ``DRJIT_LIBLLVM_PATH`` that cannot work (missing file, LLVM < 16) is removed before
    Dr.Jit sees it (Dr.Jit would print its own loader errors at import) and reported as one line
    when an LLVM variant is selected; CUDA variants run without it.
    """
    global _unusable_llvm, _unusable_lanes
    user_path = os.environ.get("DRJIT_LIBLLVM_PATH", "").strip()
    if user_path:
        _unusable_llvm = unusable_llvm_reason(user_path)
        if _unusable_llvm:
            del os.environ["DRJIT_LIBLLVM_PATH"]
    else:  # unset or empty: psdr's own search
        os.environ.pop("DRJIT_LIBLLVM_PATH", None)
        lib = find_libllvm()
        if lib:
            os.environ["DRJIT_LIBLLVM_PATH"] = lib
    if "DRJIT_CACHE_DIR" not in os.environ:
        cache = default_cache_dir()
        try:
            os.makedirs(cache, exist_ok=True)
            os.environ["DRJIT_CACHE_DIR"] = cache
        except OSError:
            pass  # Dr.Jit falls back to its own default (~/.drjit)
    _unusable_lanes = lanes_reason()  # last: it imports drjit, which reads the variables above


def lanes_reason() -> str | None:
    """Applies ``PSDR_LLVM_LANES`` (:mod:`psdr_cli.support.llvm_target`) before Dr.Jit compiles anything;
    returns None, or the one-line reason it cannot, reported when an LLVM variant is selected."""
    try:
        lanes = llvm_target.requested_lanes()
        return None if lanes is None else llvm_target.force_lanes(lanes)
    except Exception as exc:  # noqa: BLE001 - a bad value, or Dr.Jit's library not loadable: one line later
        return str(exc) if isinstance(exc, ValueError) else f"PSDR_LLVM_LANES: cannot set Dr.Jit's target ({exc})"


def _require_llvm() -> None:
    if _unusable_llvm:
        raise PsdrError(_unusable_llvm)
    if _unusable_lanes:
        raise PsdrError(_unusable_lanes)
    path = os.environ.get("DRJIT_LIBLLVM_PATH")
    if path:
        reason = unusable_llvm_reason(path)
        if reason:
            raise PsdrError(reason)
        return
    raise PsdrError(f"no libLLVM >= {MIN_LLVM} found; install one with "
                    f"'apt-get install {LLVM_PACKAGE}' (or set DRJIT_LIBLLVM_PATH)")


def cuda_available() -> bool:
    """True when Dr.Jit can use a CUDA device."""
    import drjit as dr  # deferred on purpose: configure_environment() must run before drjit loads
    try:
        return bool(dr.has_backend(dr.JitBackend.CUDA))
    except Exception:  # noqa: BLE001 - any driver failure means "no CUDA"
        return False




def select_variant(variant: str = "auto") -> str:
    """Activate a Mitsuba variant and return its name.

    ``auto`` picks ``cuda_ad_rgb`` when a CUDA device works and ``llvm_ad_rgb`` otherwise. The
    environment variable ``PSDR_VARIANT`` overrides the experiment's choice.
    """
    variant = os.environ.get("PSDR_VARIANT", variant) or "auto"
    if variant not in VARIANTS:
        raise PsdrError(f"unknown variant '{variant}' (expected {', '.join(VARIANTS)})")
    if variant == "auto":
        variant = "cuda_ad_rgb" if cuda_available() else "llvm_ad_rgb"
    if variant.startswith("llvm"):
        _require_llvm()
    import mitsuba as mi  # deferred on purpose: Dr.Jit must be configured (libLLVM path) before it loads
    if mi.variant() != variant:
        try:
            mi.set_variant(variant)
        except Exception as exc:  # noqa: BLE001
            raise PsdrError(f"cannot activate Mitsuba variant '{variant}': {exc}") from exc
    return variant


@contextmanager
def optimization_threads():
    """Run the block with ``PSDR_OPTIMIZE_THREADS`` Dr.Jit CPU threads (default 1).

    With more than one thread, Dr.Jit's LLVM backend accumulates reverse-mode gradients (and guide
    statistics) with atomic scatter-adds whose order depends on thread scheduling, so two runs
    differ in the last bits; the optimisation amplifies that (remeshing and boundary sampling are
    discontinuous in the vertices) to percent-level loss differences. One thread makes
    ``psdr optimize`` bit-reproducible (docs/optimize.md, "Reproducibility")."""
    import drjit as dr  # deferred on purpose: configure_environment() must run before drjit loads
    value = os.environ.get("PSDR_OPTIMIZE_THREADS", "1").strip()
    if not value.isdigit() or int(value) < 1 or int(value) > 1024:
        raise PsdrError(f"PSDR_OPTIMIZE_THREADS: expected a number of threads >= 1, got '{value}'")
    before = dr.thread_count()
    dr.set_thread_count(int(value))
    try:
        yield int(value)
    finally:
        dr.set_thread_count(before)


def activate(exp) -> str:
    """Activate an experiment's Mitsuba variant (``variant: auto``: CUDA when present, else LLVM)."""
    return select_variant(exp.variant)


@contextmanager
def decoding_threads(minimum: int = 2):
    """Run the block with at least ``minimum`` Dr.Jit CPU threads. Mitsuba decodes some image
    files (EXR) on Dr.Jit's thread pool and deadlocks when the pool has a single thread, as it has
    inside ``psdr optimize`` (:func:`optimization_threads`); file loading is no AD work, so the
    extra thread does not affect reproducibility."""
    import drjit as dr  # deferred on purpose: configure_environment() must run before drjit loads
    before = dr.thread_count()
    if before < minimum:
        dr.set_thread_count(minimum)
    try:
        yield
    finally:
        if before < minimum:
            dr.set_thread_count(before)
