"""Owns the hand-over of numpy arrays to Dr.Jit in 64-byte aligned memory, so that the kernels
reading them do not change. Reads numpy arrays; writes aligned copies of them.

Dr.Jit (1.x, LLVM backend) does not copy a numpy array given to an array constructor such as
``mi.UInt32(a)``: it maps the array's memory. A kernel that loads from mapped memory declares
the load ``align 64`` when the address is a multiple of 64 bytes and ``align 1`` otherwise, and
that is part of the kernel's source, so of its hash. numpy aligns its allocations to 16 bytes
only, so the same traced code fed freshly converted arrays would become a different kernel
whenever one of them lands on another alignment (measured in docs/optimize.md, "Kernels
compiled once").

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
