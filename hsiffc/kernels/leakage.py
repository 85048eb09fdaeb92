"""Compiled per-pixel kernels of the leakage model ``dY/dt = k - a e^{bY}`` (paper eq. 2).

These are *the* implementations behind :mod:`hsiffc.leakage.model` (its public functions validate and
broadcast, then call a kernel here; the inversion is in :mod:`hsiffc.kernels.inversion`); the
per-point functions (``response_point``, ``alpha_paper_point``, ...) are public so that other
compiled code (e.g. a per-pixel calibration fit) evaluates the model with exactly the same
arithmetic.

Precision: everything is computed in float64 (inputs may be float32 or float64). The
response keeps ~1e-13 DN (tests: against ``solve_ivp`` and against the previous numpy form);
alpha is computed in float64 and may be stored as float32 (1e-7 relative, far below any
threshold's meaning).

Kernels run a ``prange`` loop over blocks of :data:`BLOCK` pixels, each a compiled block
function: a branch-free loop (vectorised by LLVM, 4 doubles per instruction on AVX2) for the
common case, then a second loop repairs the rare pixels it cannot (over/underflow: the
log-domain form) while the block is in cache. (LLVM does not vectorise the same loop written
directly in the ``prange`` body.)

The response's vector loops call the short, range-restricted exponentials and logarithm of
:mod:`~hsiffc.kernels.vmath` (``exp_clamped``, ``expm1_clamped``, ``log_positive``: no
special-value selects, degree-11 and fdlibm's 7-term polynomials; their results are screened
by the ``ok`` test and repaired; their ulp errors against 50-digit arithmetic are tested in
``tests/kernels/test_vmath_short.py``).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit, prange

from ..data.dq import DQ
from .bands import ROWS, add_row, fold_block
from .launch import JIT_OPTIONS, Kernel
from .operands import at, part
from .vmath import exp, exp_clamped, expm1, expm1_clamped, log, log_positive, logaddexp

__all__ = ["BLOCK", "BandSums", "FlagOutputs", "FlagPlanes", "FlagRule", "PixelModel",
           "alpha_flags_kernel", "alpha_flags_sums_kernel", "alpha_model_kernel",
           "alpha_model_point", "alpha_paper_kernel", "alpha_paper_point", "leakage_bits",
           "response_fast", "response_kernel", "response_point", "response_robust"]

BLOCK = 4096
# Only the kernels (entry points, see launch.Kernel) are cached on disk. The per-point
# functions are compiled into each kernel that uses them: a cached function is machine code,
# which LLVM cannot inline (and vectorise) into a caller compiled later, and would go stale
# when a file it inlines changes. The vector-path ones are inlined already in numba's IR.
_JIT = {**JIT_OPTIONS, "cache": False}
_INL = {**_JIT, "inline": "always"}

# DQ bits as plain ints for compiled code
_NONFINITE = int(DQ.NONFINITE)
_SATURATED = int(DQ.SATURATED)
_LEAKAGE = int(DQ.LEAKAGE)


# -- the response ----------------------------------------------------------------------------

@njit(**_INL)
def _response_terms(t, k, a, b, d):
    """(leak, e0) of :func:`response_fast`: the two terms of ``e^{-bY}``, the exponentials'
    half of the response (see :func:`_response_block` for why it is a function of its own).

    Both exponentials by the clamped forms of :mod:`~hsiffc.kernels.vmath` (the sum is kept
    only within [1e-290, 1e290], where they give what the full forms give, see
    :func:`~hsiffc.kernels.vmath.exp_clamped`); NaN in any input makes e0 NaN."""
    x = b * k * t
    ix = 1.0 / x  # beside the exponentials (it depends on the inputs only)
    em = -expm1_clamped(-x)
    phi = em * ix if x > 0.0 else 1.0
    leak = a * b * t * phi
    e0 = exp_clamped(-b * d - x)
    return leak, e0


@njit(**_INL)
def _response_level(leak, e0, t, k, b, d):
    """(Y, ok) of :func:`response_fast` from its (leak, e0): the logarithm's half."""
    q = leak / e0  # the leakage term relative to the first
    z = e0 + leak
    ib = 1.0 / b
    lin = q <= 1.0
    w = 1.0 + q if lin else z
    # log1p(q) in the linear domain (the rounding error of 1 + q folded in), log(z) beyond;
    # w is in [1, 2] or is z, a positive normal double wherever ok
    lw = log_positive(w, (q - (w - 1.0)) if lin else 0.0)
    y = ((d + k * t) if lin else 0.0) - lw * ib
    ok = (z >= 1e-290) and (z <= 1e290)
    return y, ok


@njit(**_INL)
def response_fast(t, k, a, b, d):
    """(Y, ok): the response in the linear domain, branch-free.

    With x = b k t, ``e^{-bY} = e^{-bd-x} + a b t phi(x)``, phi(x) = (1 - e^{-x}) / x. While
    the leakage term q (relative to the first) is at most 1, ``Y = d + k t - log1p(q) / b``
    (exact in the linear regime); beyond it ``Y = -log(sum) / b``. ``ok`` is False where the
    sum under/overflows or is NaN (then use :func:`response_robust`).
    """
    leak, e0 = _response_terms(t, k, a, b, d)
    return _response_level(leak, e0, t, k, b, d)


@njit(**_JIT)
def response_robust(t, k, a, b, d):
    """The response in the log domain: finite for any b k t, a/k, k = 0 and starting levels
    above the dynamic saturation level (``logaddexp`` of the two log terms)."""
    x = b * k * t
    lphi = -0.5 * x if x < 1e-8 else log(-expm1(-x) / x)
    return -logaddexp(-b * d - x, log(a) + log(b) + log(t) + lphi) / b


@njit(**_JIT)
def response_point(t, k, a, b, d):
    """Model response (DN) at one point: the fast form, the log-domain form where it fails."""
    y, ok = response_fast(t, k, a, b, d)
    return y if ok else response_robust(t, k, a, b, d)


@njit(**_JIT)
def _response_block(t, k, a, b, d, out):
    """:func:`response_point` over one block: the vectorised fast form, then the log-domain
    form where it failed (NaN marks those), while the block is still in cache; returns how
    many inputs are outside the model's domain (t, k or a < 0; b <= 0; NaN not counted),
    counted in a loop of its own (in the first one it would slow the vector code).

    The fast form runs as two loops, the exponentials' half into a block-sized buffer, then
    the logarithm's half: in one loop the vector code has more values live than AVX2 has
    registers and spills them (the split gives the same bits; the repair scan below is skipped
    where nothing failed). The division q = leak / e0 sits in the second loop, whose
    dependency chain is the shorter."""
    n = out.shape[0]
    leaks = np.empty(n)
    e0s = np.empty(n)
    for i in range(n):
        leaks[i], e0s[i] = _response_terms(at(t, i), at(k, i), at(a, i), at(b, i), at(d, i))
    for i in range(n):
        y, ok = _response_level(leaks[i], e0s[i], at(t, i), at(k, i), at(b, i), at(d, i))
        out[i] = y if ok else np.nan
    negative = 0
    b_bad = 0
    failed = 0  # counted beside the domain, so that a block with none skips the repair scan
    for i in range(out.shape[0]):
        negative += (np.int64(at(t, i) < 0.0) | np.int64(at(k, i) < 0.0)
                     | np.int64(at(a, i) < 0.0))
        b_bad += np.int64(at(b, i) <= 0.0)
        failed += np.int64(out[i] != out[i])
    if failed:
        for i in range(out.shape[0]):
            if out[i] != out[i]:
                out[i] = response_robust(at(t, i), at(k, i), at(a, i), at(b, i), at(d, i))
    return negative, b_bad


def _response_loop(t, k, a, b, d, out):
    """``out[i] = Y(t, k, a, b, d)[i]``; each input a scalar or a flat array like ``out``.
    Returns the counts of inputs outside the model's domain (t, k or a < 0; b <= 0), so that
    the caller checks them without passes of its own."""
    n = out.shape[0]
    negative = 0
    b_bad = 0
    for blk in prange((n + BLOCK - 1) // BLOCK):
        i0 = blk * BLOCK
        i1 = min(n, i0 + BLOCK)
        neg, bb = _response_block(part(t, i0, i1), part(k, i0, i1), part(a, i0, i1),
                                  part(b, i0, i1), part(d, i0, i1), out[i0:i1])
        negative += neg
        b_bad += bb
    return negative, b_bad


response_kernel = Kernel(_response_loop, 5)


# -- the leakage percentage alpha ------------------------------------------------------------

@njit(**_INL)
def alpha_model_point(y, k, a, b):
    """Model alpha ``100 a e^{bY} / k`` (percent, eq. 4 with the model's k), log domain."""
    return 100.0 * exp(log(a) + b * y - log(k))


@njit(**_INL)
def alpha_paper_point(y, t, a, b, d):
    """Paper alpha ``100 a e^{bY} / ((Y - d) / t)`` (percent); inf where the signal or t is
    not positive (no light rate can be estimated).

    One exponential and one division (the log-domain form took two logs more on the pixel's
    chain of dependent operations): ``e^{bY}`` as the square of ``E = e^{bY / 2}``, applied
    as ``((100 a t / s) E) E`` so that no factor overflows before the result does (``E`` is
    finite for ``bY`` up to 1416; beyond, ``E`` is inf, so alpha is too). ``E`` comes from
    :func:`~hsiffc.kernels.vmath.exp_clamped` (1 ulp, one 2^n factor: a shorter chain than
    :func:`~hsiffc.kernels.vmath.exp`, whose two factors reach subnormal results alpha never
    needs; the stored float32 alpha is the same with either).
    """
    s = y - d
    x = 0.5 * b * y
    e = np.inf if x > 708.0 else exp_clamped(x)  # below -708 alpha underflows to 0 either way
    alpha = ((100.0 * a * t / s) * e) * e
    return alpha if (s > 0.0 and t > 0.0) else np.inf


@njit(**_JIT)
def _alpha_model_block(y, k, a, b, out):
    for i in range(out.shape[0]):
        out[i] = alpha_model_point(at(y, i), at(k, i), at(a, i), at(b, i))


def _alpha_model_loop(y, k, a, b, out):
    """:func:`alpha_model_point` over flat operands into ``out``, per block of
    :data:`BLOCK` (the loop of a block vectorises; the same loop in a ``prange`` body does
    not)."""
    n = out.shape[0]
    for blk in prange((n + BLOCK - 1) // BLOCK):
        i0 = blk * BLOCK
        i1 = min(n, i0 + BLOCK)
        _alpha_model_block(part(y, i0, i1), part(k, i0, i1), part(a, i0, i1), part(b, i0, i1),
                           out[i0:i1])


alpha_model_kernel = Kernel(_alpha_model_loop, 4)


@njit(**_JIT)
def _alpha_paper_block(y, t, a, b, d, out):
    for i in range(out.shape[0]):
        out[i] = alpha_paper_point(at(y, i), at(t, i), at(a, i), at(b, i), at(d, i))


def _alpha_paper_loop(y, t, a, b, d, out):
    """:func:`alpha_paper_point` over flat operands into ``out`` (float32 or float64), per
    block of :data:`BLOCK`."""
    n = out.shape[0]
    for blk in prange((n + BLOCK - 1) // BLOCK):
        i0 = blk * BLOCK
        i1 = min(n, i0 + BLOCK)
        _alpha_paper_block(part(y, i0, i1), part(t, i0, i1), part(a, i0, i1), part(b, i0, i1),
                           part(d, i0, i1), out[i0:i1])


alpha_paper_kernel = Kernel(_alpha_paper_loop, 5)


# -- validity flags ---------------------------------------------------------------------------
# The kernels take their operands in named groups (numba types a named tuple per combination
# of its members' types, None included); each kernel unpacks them and hands every block to
# its block function as separate arguments: numba removes the branches of a None operand only
# where it is an argument, and that keeps the block loop free of conditional loads.

class PixelModel(NamedTuple):
    """Per-pixel operands of the leakage model: flat arrays of every pixel or scalars
    (:func:`~hsiffc.kernels.operands.flat_operands`)."""

    y: object  #: response, DN
    t: object  #: exposure, ms
    a: object  #: leakage amplitude, DN/ms
    b: object  #: leakage exponent, 1/DN
    d: object  #: dark under the response, DN


class FlagRule(NamedTuple):
    """How the validity flags are set (:func:`leakage_bits`)."""

    threshold: float  #: alpha (percent) over which LEAKAGE is set
    full_scale: float  #: response (DN) from which SATURATED is set
    const_bits: int  #: bits every pixel gets (OUT_OF_DOMAIN)


class FlagPlanes(NamedTuple):
    """DQ planes OR-ed into the result: flat uint32 arrays, or None where absent."""

    pix: object  #: the calibration's pixel flags
    dq_in: object  #: the frame's DQ so far
    extra: object  #: more bits (a flat field's own)


class FlagOutputs(NamedTuple):
    """Where a validity pass reads alpha from or writes it to, and writes DQ and signal: flat
    arrays; exactly one of ``alpha_in`` and ``alpha_out`` is None, ``signal`` may be."""

    alpha_in: object  #: float32 alpha (percent) given
    alpha_out: object  #: float32 alpha (percent) computed here
    dq: object  #: uint32 DQ
    signal: object  #: float32 ``y - d``, or None


class BandSums(NamedTuple):
    """The per-band sums a validity pass also takes (:func:`alpha_flags_sums_kernel`)."""

    band_map: object  #: (H, W) int64 band index
    period: int  #: the band map's row period (> 0)
    sums: object  #: (blocks, bands) float64, written
    counts: object  #: (blocks, bands) int64, written


@njit(**_INL)
def leakage_bits(alpha, y, threshold, full_scale):
    """DQ bits of one response from its alpha: LEAKAGE where alpha is over the threshold or
    not a number, SATURATED where the response is at full scale."""
    bits = _LEAKAGE if not (alpha <= threshold) else 0
    return bits | (_SATURATED if y >= full_scale else 0)


@njit(**_JIT)
def _alpha_flags_block(y, t, a, b, d, threshold, full_scale, const_bits, pix, dq_in, extra,
                       alpha_in, alpha_out, dq_out, signal_out):
    # The optional planes are None or arrays: numba compiles each combination with the
    # branches of the absent ones removed, so the loop has no conditional loads and
    # vectorises (with run-time flags it does not).
    for i in range(dq_out.shape[0]):
        yi = at(y, i)
        if signal_out is not None:  # np.subtract(y, d, dtype=float32): both rounded first
            signal_out[i] = np.float32(yi) - np.float32(at(d, i))
        alpha = 0.0  # (numba prunes "x is not None" only where x is None: two tests)
        if alpha_in is not None:
            alpha = np.float64(alpha_in[i])
        if alpha_out is not None:
            alpha = alpha_paper_point(yi, at(t, i), at(a, i), at(b, i), at(d, i))
            alpha_out[i] = alpha
        bits = leakage_bits(alpha, yi, threshold, full_scale) | const_bits
        if pix is not None:
            bits |= pix[i]
        if dq_in is not None:
            bits |= dq_in[i]
        if extra is not None:
            bits |= extra[i]
        dq_out[i] = bits


def _alpha_flags_loop(model, rule, planes, outputs):
    """Paper alpha into ``outputs.alpha_out`` (or, given ``outputs.alpha_in``, alpha read
    from it) and the DQ of every pixel: :func:`leakage_bits` | ``const_bits`` | the
    ``planes``; with ``outputs.signal``, also ``y - d`` in float32 (the dark subtraction of
    the same pixels, in the same pass); per block of :data:`BLOCK`. Operands:
    :class:`PixelModel`, :class:`FlagRule`, :class:`FlagPlanes`, :class:`FlagOutputs`."""
    y, t, a, b, d = model
    threshold, full_scale, const_bits = rule
    pix, dq_in, extra = planes
    alpha_in, alpha_out, dq_out, signal_out = outputs
    n = dq_out.shape[0]
    for blk in prange((n + BLOCK - 1) // BLOCK):
        i0 = blk * BLOCK
        i1 = min(n, i0 + BLOCK)
        _alpha_flags_block(part(y, i0, i1), part(t, i0, i1), part(a, i0, i1), part(b, i0, i1),
                           part(d, i0, i1), threshold, full_scale, const_bits,
                           part(pix, i0, i1), part(dq_in, i0, i1), part(extra, i0, i1),
                           part(alpha_in, i0, i1), part(alpha_out, i0, i1), dq_out[i0:i1],
                           part(signal_out, i0, i1))


alpha_flags_kernel = Kernel(_alpha_flags_loop, (3, 2))


_SUB = 4  # rows per call of the block function in _alpha_flags_sums_loop


def _alpha_flags_sums_loop(model, rule, planes, outputs, by_band):
    """:func:`_alpha_flags_loop` (alpha computed: ``outputs.alpha_in`` is None) over a 2-D
    frame given as flat operands (rows of ``band_map.shape[1]`` pixels) by blocks of
    :data:`~hsiffc.kernels.bands.ROWS` rows, which also adds each row's finite ``y`` at the
    pixels whose DQ comes out 0 into ``sums/counts[block, band]`` (``by_band``, a
    :class:`BandSums`): the partial sums of
    :func:`~hsiffc.kernels.bands.band_sums` of ``y`` with ``good = dq == 0`` and row period
    ``period`` (> 0), the same values added in the same order
    (:func:`~hsiffc.kernels.bands.add_row`, :func:`~hsiffc.kernels.bands.fold_block`). A
    two-point FFC's eq. (5) level of the test frame thus comes out of this pass instead of a
    second pass over the frame."""
    y, t, a, b, d = model
    threshold, full_scale, const_bits = rule
    pix, dq_in, extra = planes
    alpha_out, dq_out, signal_out = outputs.alpha_out, outputs.dq, outputs.signal
    band_map, period, sums, counts = by_band
    H, W = band_map.shape
    for blk in prange((H + ROWS - 1) // ROWS):
        y0 = blk * ROWS
        y1 = min(H, y0 + ROWS)
        col_sum = np.zeros((period, W))
        col_count = np.zeros((period, W), np.int32)
        for r0 in range(y0, y1, _SUB):  # a few rows flagged, then added while in cache
            r1 = min(y1, r0 + _SUB)
            i0 = r0 * W
            i1 = r1 * W
            _alpha_flags_block(part(y, i0, i1), part(t, i0, i1), part(a, i0, i1),
                               part(b, i0, i1), part(d, i0, i1), threshold, full_scale,
                               const_bits, part(pix, i0, i1), part(dq_in, i0, i1),
                               part(extra, i0, i1), None, alpha_out[i0:i1], dq_out[i0:i1],
                               part(signal_out, i0, i1))
            for row in range(r0, r1):
                phase = (row - y0) % period
                add_row(col_sum[phase], col_count[phase], y[row * W:row * W + W],
                        dq_out[row * W:row * W + W], 0)
        fold_block(col_sum, col_count, band_map[y0:y0 + min(period, y1 - y0)], sums[blk],
                   counts[blk])


alpha_flags_sums_kernel = Kernel(_alpha_flags_sums_loop, (3, 2))
