"""numpy arrays handed to Dr.Jit without changing the kernels that read them.

Dr.Jit (1.x, LLVM backend) does not copy a numpy array given to an array constructor such as
``mi.UInt32(a)``: it maps the array's memory. A kernel that loads from mapped memory declares
the load ``align 64`` when the address is a multiple of 64 bytes and ``align 1`` otherwise, and
that is part of the kernel's source, so of its hash. numpy aligns its allocations to 16 bytes
only: the same traced code, fed freshly converted index arrays (edge lists, curve ids, adjoint
images) every iteration, becomes a different kernel whenever one of them lands on another
alignment, and is compiled again. Measured without aligned copies: 2–4 kernels per reverse pass
(0.16–0.37 s of a 0.53–0.78 s gradient) in the first iterations on a fixed bunny shape (1642
vertices, four views, one thread), until the on-disk kernel cache holds every variant (a
300-iteration run of ``configs/reconstruct_bunny.yaml`` from an empty cache compiles 156 kernels
without them and 121 with them, in the same 109 s: on a warm cache the cost is gone either way).

:func:`jit_array` copies the values into a 64-byte aligned numpy buffer first (the mapped array
keeps that buffer alive), so every load is ``align 64`` and a kernel is compiled once per run.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

#: Alignment (bytes) of the buffers handed to Dr.Jit: a cache line, what its own allocator gives.
ALIGNMENT = 64


def aligned_copy(values, dtype) -> np.ndarray:
    """A C-contiguous copy of ``values`` as ``dtype`` whose data starts on an ``ALIGNMENT``-byte
    boundary (a view into a slightly larger buffer, which the view keeps alive)."""
    a = np.asarray(values, dtype)
    buffer = np.empty(a.nbytes + ALIGNMENT, np.uint8)
    start = (-buffer.ctypes.data) % ALIGNMENT
    out = buffer[start: start + a.nbytes].view(dtype).reshape(a.shape)
    out[...] = a
    return out


def jit_array(cls, values):
    """``cls(values)`` for a Dr.Jit array type ``cls`` (``mi.Float``, ``mi.UInt32``, ``mi.Bool``,
    ``mi.TensorXf``…) from numpy ``values``, from 64-byte aligned memory (module docstring)."""
    dtype = {"Float": np.float32, "Float32": np.float32, "UInt32": np.uint32, "UInt": np.uint32,
             "Int32": np.int32, "Int": np.int32, "Bool": np.bool_, "TensorXf": np.float32,
             "Float64": np.float64}[cls.__name__]
    return cls(aligned_copy(values, dtype))


def concat(parts):
    """The arrays ``parts`` (one Dr.Jit type: ``mi.Float``, ``mi.UInt32``, ``mi.Point2f``…, AD or
    not) end to end. ``dr.concat`` writes part j at ``arange + offset_j`` with the offsets as literals
    of the kernel, which is then compiled again whenever the parts' widths change (curve counts
    change every iteration); here the offsets are opaque."""
    if len(parts) == 1:
        return parts[0]
    first = parts[0]
    if dr.depth_v(first) > 1:
        return type(first)(*(concat([p[i] for p in parts]) for i in range(len(first))))
    out = dr.empty(type(first), sum(dr.width(p) for p in parts))
    offset = 0
    for p in parts:
        index = dr.arange(mi.UInt32, dr.width(p)) + dr.opaque(mi.UInt32, offset)
        dr.scatter(out, p, index, mode=dr.ReduceMode.Permute)
        offset += dr.width(p)
    return out
