"""The SIMD target of Dr.Jit's LLVM backend: how many float lanes its kernels process at once.

Dr.Jit compiles its CPU kernels for the host: 16 lanes with AVX-512, 8 with AVX2. The rounding of
a few operations depends on that choice (with AVX-512 the reciprocal square root starts from
``vrsqrt14``, with AVX2 from ``vrsqrtps``), so two machines give results that agree only up to
rounding. ``PSDR_LLVM_LANES`` (4, 8 or 16) makes every kernel of the process use one target of
:data:`TARGETS` instead: the same results on any CPU that has the instructions, and a way to run
the test suite as an AVX2 machine would on an AVX-512 one.

Dr.Jit 1.5 sets this target only through its C interface, ``jit_llvm_set_target(cpu, features,
width)`` of ``libdrjit-core.so``; it must be called after ``drjit`` is imported (the import sets
the host's target) and before the LLVM backend compiles its first kernel, so :func:`force_lanes`
runs when ``psdr_cli`` is imported.
"""
from __future__ import annotations

import ctypes
import os

#: Lanes → (LLVM CPU name, LLVM feature string, the /proc/cpuinfo flag the host needs).
TARGETS = {
    4: ("nehalem", "+sse2,+sse3,+ssse3,+sse4.1,+sse4.2,+popcnt,+cx16,-avx,-avx2,-fma,-avx512f,-evex512", "sse4_2"),
    8: ("haswell", "+sse2,+sse3,+ssse3,+sse4.1,+sse4.2,+popcnt,+cx16,+avx,+avx2,+fma,+f16c,+bmi,+bmi2,+lzcnt,"
                   "+movbe,-avx512f,-evex512", "avx2"),
    16: ("skylake-avx512", "+sse2,+sse3,+ssse3,+sse4.1,+sse4.2,+popcnt,+cx16,+avx,+avx2,+fma,+f16c,+bmi,+bmi2,"
                           "+lzcnt,+movbe,+avx512f,+avx512cd,+avx512dq,+avx512bw,+avx512vl,+evex512", "avx512f"),
}

#: The environment variable that chooses a target.
LANES_VARIABLE = "PSDR_LLVM_LANES"

_CORE = "libdrjit-core.so"


def requested_lanes() -> int | None:
    """The lanes ``PSDR_LLVM_LANES`` asks for (None: unset or empty, the host's own target).
    Raises ValueError with a one-line reason for any other value."""
    value = os.environ.get(LANES_VARIABLE, "").strip()
    if not value:
        return None
    if not value.isdigit() or int(value) not in TARGETS:
        raise ValueError(f"{LANES_VARIABLE}: expected one of {', '.join(map(str, TARGETS))} (SIMD lanes of "
                         f"Dr.Jit's CPU kernels) or unset, got '{value}'")
    return int(value)


def cpu_flags() -> set:
    """The host CPU's feature flags (the ``flags`` line of /proc/cpuinfo; empty where there is none)."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("flags"):
                    return set(line.split(":", 1)[1].split())
    except OSError:
        pass
    return set()


def core_library():
    """ctypes handle of Dr.Jit's core library (``drjit`` imported: its import sets up the LLVM
    backend's default target, which a target set before would not survive)."""
    import drjit  # deferred on purpose: backend.configure_environment sets DRJIT_LIBLLVM_PATH first
    path = os.path.join(os.path.dirname(drjit.__file__), _CORE)
    return ctypes.CDLL(path) if os.path.exists(path) else None


def _function(lib, name: str, restype, argtypes=()):
    fn = getattr(lib, name)
    fn.restype, fn.argtypes = restype, list(argtypes)
    return fn


def current_target(lib=None) -> tuple:
    """(CPU name, vector width) that Dr.Jit's LLVM backend compiles for now."""
    lib = lib or core_library()
    cpu = _function(lib, "_Z19jit_llvm_target_cpuv", ctypes.c_char_p)()
    width = _function(lib, "_Z21jit_llvm_vector_widthv", ctypes.c_uint32)()
    return (cpu or b"").decode(), int(width)


def force_lanes(lanes: int) -> str | None:
    """Make Dr.Jit's LLVM kernels use the target of :data:`TARGETS` with ``lanes`` lanes; returns
    None, or a one-line reason why it cannot (the CPU lacks the instructions, the symbol is
    missing)."""
    cpu, features, flag = TARGETS[lanes]
    if flag not in cpu_flags():
        return f"{LANES_VARIABLE}={lanes}: this CPU has no {flag.upper().replace('_', '.')} ({cpu} target)"
    lib = core_library()
    if lib is None:
        return f"{LANES_VARIABLE}={lanes}: Dr.Jit's {_CORE} was not found"
    try:
        set_target = _function(lib, "_Z19jit_llvm_set_targetPKcS0_j", None,
                               (ctypes.c_char_p, ctypes.c_char_p, ctypes.c_uint32))
    except AttributeError:
        return f"{LANES_VARIABLE}={lanes}: this Dr.Jit has no jit_llvm_set_target"
    set_target(cpu.encode(), features.encode(), lanes)
    if current_target(lib) != (cpu, lanes):
        return f"{LANES_VARIABLE}={lanes}: Dr.Jit kept its own target {current_target(lib)}"
    return None
