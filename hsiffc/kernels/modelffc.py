"""Compiled kernel of the model-based flat-field correction
(:func:`hsiffc.flatfield.model_based.model_ffc_apply`).

Per block of pixels: the vectorised rounds of the inversion
(:func:`~hsiffc.kernels.inversion.invert_rounds`, which give k and the model alpha), then one
pass for the blend of the two responsivity factors by alpha, the corrected value and its DQ
bits. The pixels the rounds leave (non-finite input, zero light, extreme parameters) are
inverted again by the compiled inversion (:func:`hsiffc.leakage.model.invert_response`, bracketed
scalar iteration) and corrected by :func:`model_ffc_finish` with the same
:func:`correct_point`: the scalar iteration is not compiled a second time into this kernel (it
would double its compile time). Everything in float64; outputs stored as float32 (DN,
percent).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit, prange

from ..data.dq import DQ
from .launch import JIT_OPTIONS, Kernel
from .inversion import PENDING, ROUNDS, invert_rounds
from .leakage import BLOCK, PixelModel, alpha_model_point
from .operands import at, part
from .vmath import exp

__all__ = ["CorrectionLimits", "CorrectionOutputs", "Factors", "PixelModel", "correct_point",
           "model_ffc_finish", "model_ffc_kernel", "pending_indices"]

_INL = {**JIT_OPTIONS, "cache": False, "inline": "always"}
_F32_MAX = float(np.finfo(np.float32).max)
#: float64 values at or beyond it round to an infinite float32 (the midpoint between float32's
#: largest value and 2^128 rounds to even, away from the odd largest value)
_F32_OVERFLOW = 2.0 ** 128 - 2.0 ** 103
_BELOW_DARK = int(DQ.BELOW_DARK)
_LEAKAGE = int(DQ.LEAKAGE)
_BAD = int(DQ.NONFINITE | DQ.DO_NOT_USE)


class Factors(NamedTuple):
    """The responsivity factors of :func:`correct_point`: flat arrays of every pixel or
    scalars (:func:`~hsiffc.kernels.operands.flat_operands`), and ``has_sweep``."""

    base: object  #: ``g_sweep`` (with ``has_sweep``), else the factor itself
    log_ratio: object  #: ``ln(g_flat / g_sweep)`` (0.0 without a sweep factor)
    dark_current: object  #: DN/ms
    has_sweep: bool


class CorrectionLimits(NamedTuple):
    """The scalars of the correction (:func:`correct_point`, the inversion's rounds)."""

    full_scale: float  #: DN (inf: none)
    flat_alpha: float  #: model alpha (percent) at which the flat's share is gone
    alpha_limit: float  #: model alpha (percent) over which LEAKAGE is set
    below_tol: float  #: DN under the dark before BELOW_DARK is set
    tol_dn: float  #: the inversion's tolerance, DN


class CorrectionOutputs(NamedTuple):
    """Flat arrays the correction writes: ``out`` float32 DN, ``dq`` uint32, ``alpha``
    float32 percent."""

    out: object
    dq: object
    alpha: object


@njit(**_INL)
def correct_point(k, flags, alpha, y, t, d, base, log_ratio, has_sweep, dc, flat_alpha,
                  alpha_limit, below_tol):
    """(corrected DN, DQ bits, alpha percent) of one pixel from its inverted rate ``k``, the
    inversion's DQ ``flags`` and its model alpha (percent, ``100 a e^{bY} / k``).

    The signal is ``(k - dc) t`` (``dc`` the dark current; ``y - d`` at and below the
    zero-light level, read noise kept linear); the factor moves from the flat's ``g_flat`` to
    the sweep's ``g_sweep`` as the model alpha grows, ``ln f = ln g_sweep + w (ln g_flat -
    ln g_sweep)``, ``w = max(0, 1 - alpha / flat_alpha)``: ``base`` is ``g_sweep`` and
    ``log_ratio`` ``ln(g_flat / g_sweep)`` (with ``has_sweep`` False, ``base`` is the factor).
    """
    below = (flags & _BELOW_DARK) != 0
    signal = (y - d) if (below or not k > 0.0) else (k - dc) * t
    alpha = np.inf if alpha != alpha else alpha
    factor = base
    if has_sweep:
        w = min(max(1.0 - alpha / flat_alpha, 0.0), 1.0)
        factor = base * exp(w * log_ratio)
    out = signal * factor
    dq = flags & ~_BELOW_DARK
    dq |= _BELOW_DARK if (below and y < d - below_tol) else 0
    dq |= _LEAKAGE if (not alpha <= alpha_limit and not below) else 0
    finite = abs(out) < _F32_OVERFLOW  # finite once stored as float32
    dq |= 0 if finite else _BAD
    return (out if finite else 0.0), dq, min(alpha, _F32_MAX)


@njit(**{**JIT_OPTIONS, "cache": False})
def _model_ffc_block(y, t, a, b, d, base, log_ratio, dark_current, has_sweep, full_scale,
                     flat_alpha, alpha_limit, below_tol, tol_dn, out, dq_out, alpha_out):
    """:func:`correct_point` for one block (operands as :func:`~.operands.part` gives them)
    from the vectorised rounds of the inversion (:func:`~.inversion.invert_rounds`); pixels
    they leave are marked :data:`PENDING`. Returns how many."""
    m = out.shape[0]
    k = np.empty(m)
    alpha = np.empty(m)
    # an int64, as the inversion kernel passes it (a literal compiles invert_rounds anew)
    invert_rounds(y, t, a, b, d, full_scale, np.inf, tol_dn, np.int64(ROUNDS), k, dq_out,
                  alpha)
    left = 0
    for j in range(m):
        yi = at(y, j)
        flags = dq_out[j]
        o, q, al = correct_point(k[j], flags & ~PENDING, alpha[j], yi, at(t, j), at(d, j),
                                 at(base, j), at(log_ratio, j), has_sweep, at(dark_current, j),
                                 flat_alpha, alpha_limit, below_tol)
        # above full scale the inversion's alpha is at full scale, not at the response
        unsettled = (flags & PENDING) != 0 or yi > full_scale
        out[j] = o
        alpha_out[j] = al
        dq_out[j] = q | (PENDING if unsettled else 0)
        left += 1 if unsettled else 0
    return left


def _model_ffc_loop(model, factors, limits, outputs, block_left):
    """:func:`correct_point` of every pixel into ``outputs`` (:class:`CorrectionOutputs`);
    operands :class:`~hsiffc.kernels.leakage.PixelModel`, :class:`Factors` and
    :class:`CorrectionLimits`, per block of :data:`~hsiffc.kernels.leakage.BLOCK` pixels.
    Pixels the vectorised rounds leave are marked :data:`PENDING` in ``outputs.dq`` for
    :func:`model_ffc_finish`; returns how many, and ``block_left[block]`` says how many in
    each block (only those blocks are scanned)."""
    y, t, a, b, d = model
    base, log_ratio, dark_current, has_sweep = factors
    full_scale, flat_alpha, alpha_limit, below_tol, tol_dn = limits
    out, dq_out, alpha_out = outputs
    n = out.shape[0]
    pending = 0
    for blk in prange((n + BLOCK - 1) // BLOCK):
        i0 = blk * BLOCK
        i1 = min(n, i0 + BLOCK)
        left = _model_ffc_block(
            part(y, i0, i1), part(t, i0, i1), part(a, i0, i1), part(b, i0, i1),
            part(d, i0, i1), part(base, i0, i1), part(log_ratio, i0, i1),
            part(dark_current, i0, i1), has_sweep, full_scale, flat_alpha, alpha_limit,
            below_tol, tol_dn, out[i0:i1], dq_out[i0:i1], alpha_out[i0:i1])
        block_left[blk] = left
        pending += left
    return pending


model_ffc_kernel = Kernel(_model_ffc_loop, (3, 0))


def _pending_loop(dq, block_left, block, idx):
    """The indices of the pixels marked :data:`PENDING` in ``dq`` into ``idx`` (ascending),
    scanning only the blocks ``block_left`` says hold some, parallel over those blocks."""
    n_blocks = block_left.shape[0]
    start = np.zeros(n_blocks + 1, np.int64)
    for blk in range(n_blocks):
        start[blk + 1] = start[blk] + block_left[blk]
    for blk in prange(n_blocks):
        if block_left[blk] == 0:
            continue
        m = start[blk]
        for i in range(blk * block, min(dq.shape[0], (blk + 1) * block)):
            if dq[i] & PENDING:
                idx[m] = i
                m += 1


pending_kernel = Kernel(_pending_loop, 0)


def pending_indices(dq, block_left) -> np.ndarray:
    """Indices of the :data:`PENDING` pixels of a :data:`model_ffc_kernel` result, in one
    compiled pass over the blocks that hold some (a Python loop over them would be a serial
    part that keeps the correction from scaling with threads)."""
    idx = np.empty(int(block_left.sum()), np.int64)
    pending_kernel(dq, block_left, BLOCK, idx)
    return idx


def _finish_loop(idx, k, flags, model, factors, limits, outputs):
    """Correct the pixels ``idx`` (those :data:`PENDING` after :data:`model_ffc_kernel`)
    from their rates ``k`` and flags found by the bracketed scalar inversion
    (:func:`hsiffc.leakage.model.invert_response` on those pixels), in parallel (on a bright frame
    they are the saturated pixels: not few). Operands as in the kernel (flat arrays of every
    pixel, or scalars)."""
    y, t, a, b, d = model
    base, log_ratio, dark_current, has_sweep = factors
    flat_alpha, alpha_limit, below_tol = limits.flat_alpha, limits.alpha_limit, limits.below_tol
    out, dq_out, alpha_out = outputs
    for m in prange(idx.shape[0]):
        j = idx[m]
        yj = at(y, j)
        aj = at(a, j)
        bj = at(b, j)
        alpha = alpha_model_point(yj, max(k[m], 1e-300), aj, bj)
        o, q, al = correct_point(k[m], flags[m], alpha, yj, at(t, j), at(d, j), at(base, j),
                                 at(log_ratio, j), has_sweep, at(dark_current, j), flat_alpha,
                                 alpha_limit, below_tol)
        out[j] = o
        alpha_out[j] = al
        dq_out[j] = q


model_ffc_finish = Kernel(_finish_loop, 0)
