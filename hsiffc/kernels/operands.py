"""Broadcasting for the numba kernels: whole-frame operands become flat arrays, size-1 operands
become scalars, so a kernel specialises on "scalar or array" per argument and its loop
vectorises (no stride-0 gathers)."""

from __future__ import annotations

import numpy as np
from numba import types
from numba.extending import overload

from .launch import PARALLEL_MIN

__all__ = ["at", "flat_operands", "float_array", "part", "read_only"]


def float_array(x) -> np.ndarray:
    """``x`` as a float32 array if it already is one, else as float64 (no copy when possible)."""
    a = np.asarray(x)
    if a.dtype == np.float32 or a.dtype == np.float64:
        return a
    return a.astype(np.float64)


def flat_operands(*values, names=None):
    """Broadcast ``values`` and return ``(shape, operands)``.

    ``names`` (the caller's parameter names, in order) go into the error raised when the
    values do not broadcast to one shape.

    For a result of :data:`~hsiffc.kernels.launch.PARALLEL_MIN` elements or more (what the
    parallel build runs on) each operand is a Python float (the value had one element) or a
    C-contiguous 1-D float32 / float64 array of ``prod(shape)`` elements: a view when the value
    already has the full size, else a broadcast copy. Smaller results (the serial build) get
    every operand as a float64 array of the full size: copies that cost nothing at that size,
    and one compiled specialisation per kernel instead of one per mix of scalars, float32 and
    float64 (numba compiles each mix anew, and a leakage kernel's compile is long). Every array
    operand is a read-only view (:func:`read_only`). Kernels index operands with :func:`at`.
    """
    arrays = [float_array(v) for v in values]
    try:
        shape = np.broadcast_shapes(*(a.shape for a in arrays))
    except ValueError:
        labels = names or [f"operand {i}" for i in range(len(arrays))]
        listed = ", ".join(f"{n} {a.shape}" for n, a in zip(labels, arrays) if a.size != 1)
        raise ValueError(f"{listed}: these shapes do not broadcast together; give scalars or "
                         "arrays of the frame's shape") from None
    size = int(np.prod(shape, dtype=np.int64))
    if size < PARALLEL_MIN:
        return shape, [read_only(np.ascontiguousarray(np.broadcast_to(a, shape),
                                                      np.float64).reshape(-1))
                       for a in arrays]
    ops = []
    for a in arrays:
        if a.size == 1:
            ops.append(float(a.reshape(-1)[0]))
        elif a.size == size:
            ops.append(read_only(np.ascontiguousarray(a).reshape(-1)))
        else:
            ops.append(read_only(np.ascontiguousarray(np.broadcast_to(a, shape)).reshape(-1)))
    return shape, ops


def read_only(a: np.ndarray) -> np.ndarray:
    """A read-only view of ``a`` (no copy). Kernels get their input operands read-only whatever
    the caller's arrays are: numba types read-only and writable arrays apart and compiled each
    kernel once per mix (the test suite, on a clean cache, compiled the closed form's serial
    build 8 times and the inversion's 6)."""
    view = a.view()
    view.flags.writeable = False
    return view


def at(x, at_index):
    """Element ``at_index`` of a flat operand (``x`` itself for a scalar) as a float64, so
    that the arithmetic is double precision whatever the storage. Compiled away in kernels.
    (The parameter name is unusual on purpose: inlined into a ``prange`` loop it must not
    shadow the loop index.)"""
    return np.float64(x if np.ndim(x) == 0 else x[at_index])


@overload(at, inline="always")
def _at_overload(x, at_index):
    if isinstance(x, types.Array):
        return lambda x, at_index: np.float64(x[at_index])
    return lambda x, at_index: np.float64(x)


def part(x, start, stop):
    """Elements ``start:stop`` of a flat operand (``x`` itself for a scalar): a kernel's
    ``prange`` body hands each block of its operands to a compiled block function, whose loop
    from 0 LLVM vectorises (the same loop written inside the ``prange`` body it does not)."""
    return x if np.ndim(x) == 0 else x[start:stop]


@overload(part, inline="always")
def _part_overload(x, start, stop):
    if isinstance(x, types.Array):
        return lambda x, start, stop: x[start:stop]
    return lambda x, start, stop: x
