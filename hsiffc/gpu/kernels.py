"""CUDA kernels of the correction (numba-cuda), built from the CPU kernels' scalar functions.

:data:`correct` runs, per pixel, what the fused dark + alpha mask pass and the model FFC do on
the CPU: the dark subtraction, :func:`~hsiffc.kernels.leakage.alpha_paper_point` and
:func:`~hsiffc.kernels.leakage.leakage_bits`, then :func:`~hsiffc.kernels.inversion.invert_point`,
:func:`~hsiffc.kernels.leakage.alpha_model_point` and
:func:`~hsiffc.kernels.modelffc.correct_point` - the same numba functions, compiled for the
GPU. :data:`bilinear` evaluates the normalised convolution of
:mod:`hsiffc.kernels.demosaic` per output value (the tent of S1 in float32, the twice-wide S2
where S1 holds no usable sample in float64, DQ and alpha by the same rules; "nearest" and
PPID as options of the same kernel) and stores the cube in the stream's output types
(:mod:`hsiffc.gpu.pack`). :data:`band_sums`, :data:`two_point_ratio` and
:data:`two_point_apply` are the two-point FFC; :data:`band_levels`, :data:`ppi_values`,
:data:`ppi_window` and :data:`window_max` PPID's levels, pseudo-panchromatic image and alpha;
the ``median_*`` kernels the exact band medians and :data:`fill_missing` the fill.

Tolerance against the CPU path (tests/gpu/test_gpu.py in the simulator, benchmarks/gpu.py on the
device): DQ equal bit for bit; the corrected frame within 2 float32 ulps (the CPU takes most
pixels through the vectorised Halley rounds of
:func:`~hsiffc.kernels.inversion.invert_rounds`, the GPU every pixel through the bracketed
scalar iteration: both stop within 1e-9 DN of the root); the cube within 4 float32 ulps of
the frame's largest value (the CPU sums a pixel's tent in another order, and the GPU compiler
may fuse multiply-adds). The two-point FFC's test level is a float64 sum in another order:
exact for integer DN; for non-integer frames its factor may differ by one float32 ulp.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ..data.dq import DQ
from ..kernels.demosaic import EPS
from ..kernels.inversion import invert_point
from ..kernels.leakage import alpha_model_point, alpha_paper_point, leakage_bits
from ..kernels.modelffc import correct_point
from . import cuda_module
from .pack import clip_half, fold_dq8, round_u16

cuda = cuda_module()
if cuda is None:  # importable without numba-cuda (documentation, doctest collection): the
    class _NoCuda:  # kernels stay plain functions; hsiffc.gpu.require refuses to run them
        @staticmethod
        def jit(fn=None, **_):
            return fn if fn is not None else (lambda f: f)

    cuda = _NoCuda()

__all__ = ["CubeIn", "CubeOut", "FrameOut", "Lattices", "MaskTerms", "MedianFill", "ModelTerms",
           "NearestTerms", "PpidTerms", "RawFrame", "bilinear", "correct", "flag_uncertain",
           "pack2d"]

_SAT = np.uint32(DQ.SATURATED)
_BAD_INPUT = np.uint32(DQ.NONFINITE | DQ.DO_NOT_USE)
_DNU = np.uint32(DQ.DO_NOT_USE)
_F32_MAX = float(np.finfo(np.float32).max)
_NEG = np.float32(-np.inf)


# -- the kernels' operands, grouped (numba passes a named tuple's fields as the kernel's
# arguments: the same launch, fewer names to keep in order) ------------------------------------
class RawFrame(NamedTuple):
    """The frame as read, for :data:`correct`."""

    raw: object  # (H, W) any real dtype
    dq_in: object  # (H, W) uint32, read where has_dq_in
    has_dq_in: bool
    raw_full: float  # SATURATED at and above, DN
    t: float  # exposure, ms
    dark: object  # (H, W) float32, DN


class MaskTerms(NamedTuple):
    """The alpha mask's planes and rule, for :data:`correct`."""

    a32: object  # (H, W) float32, DN/ms
    b32: object  # (H, W) float32, 1/DN
    pix: object  # (H, W) uint32 pixel flags
    const_bits: int  # OUT_OF_DOMAIN or 0
    threshold: float  # percent
    full_scale_mask: float  # DN


class ModelTerms(NamedTuple):
    """The model FFC's planes and constants, for :data:`correct` (read where ``do_ffc``)."""

    do_ffc: bool
    a: object
    b: object
    base: object
    log_ratio: object
    has_sweep: bool
    dark_current: float
    full_scale: float
    flat_alpha: float
    alpha_limit: float
    below_tol: float
    tol_dn: float
    max_iter: int


class FrameOut(NamedTuple):
    """What :data:`correct` writes: the corrected frame, alpha and DQ, (H, W) each."""

    out: object
    alpha_out: object
    dq_out: object


class CubeIn(NamedTuple):
    """The corrected frame :data:`bilinear` interpolates."""

    data: object  # (H, W) float32
    dq: object  # (H, W) uint32, read where has_dq
    has_dq: bool
    alpha: object  # (H, W) float32, read where has_alpha
    has_alpha: bool


class Lattices(NamedTuple):
    """The bands' sample lattices and the phase tables of :data:`bilinear`."""

    lat_r: object
    lat_c: object
    lat_start: object
    ph: int
    pw: int
    ymod: object
    xmod: object
    wy_of: object
    wx_of: object


class CubeOut(NamedTuple):
    """Where :data:`bilinear` stores the cube, in the stream's output types."""

    cube: object
    cube_dq: object
    cube_alpha: object
    mode: int
    fold: bool


class MedianFill(NamedTuple):
    """Values with no usable sample: ``medians`` where ``has_medians``, else counted in
    ``missing`` and listed in ``miss_list``."""

    medians: object
    has_medians: bool
    missing: object
    miss_list: object


class NearestTerms(NamedTuple):
    """The "nearest" option: the pattern positions of each band and the tile offset."""

    near: bool
    pat_r: object
    pat_c: object
    pat_start: object
    oy: int
    ox: int


class PpidTerms(NamedTuple):
    """PPID: the pseudo-panchromatic image, the band levels and the alpha window."""

    use_ppi: bool
    ppi: object
    ppi_ok: object
    levels: object
    alpha_win: object


@cuda.jit
def correct(src, mask, model, dst):
    """One pixel per thread: dark, paper alpha and DQ (the mask), then with ``do_ffc`` the
    model FFC. ``raw`` is the frame as read (any real dtype); without ``dq_in`` its DQ is what
    :meth:`hsiffc.data.frame.Frame.from_raw` gives (SATURATED at ``raw_full``, non-finite values
    read as 0 with NONFINITE | DO_NOT_USE). Operands: :class:`RawFrame`, :class:`MaskTerms`,
    :class:`ModelTerms`, :class:`FrameOut`."""
    raw, dq_in, has_dq_in, raw_full, t, dark = src
    a32, b32, pix, const_bits, threshold, full_scale_mask = mask
    (do_ffc, a, b, base, log_ratio, has_sweep, dark_current, full_scale, flat_alpha,
     alpha_limit, below_tol, tol_dn, max_iter) = model
    out, alpha_out, dq_out = dst
    c, r = cuda.grid(2)  # x (fastest) along the row: coalesced
    if r >= out.shape[0] or c >= out.shape[1]:
        return
    y32 = np.float32(raw[r, c])
    bits_in = np.uint32(0)
    if not (abs(y32) < np.inf):
        y32 = np.float32(0.0)
        bits_in = _BAD_INPUT
    if has_dq_in:
        bits_in = dq_in[r, c]
    elif y32 >= raw_full:
        bits_in |= _SAT
    y = np.float64(y32)
    d32 = dark[r, c]
    d = np.float64(d32)
    alpha = alpha_paper_point(y, t, np.float64(a32[r, c]), np.float64(b32[r, c]), d)
    alpha_out[r, c] = np.float32(alpha)
    bits = np.int64(leakage_bits(alpha, y, threshold, full_scale_mask)) | const_bits
    bits |= np.int64(pix[r, c]) | np.int64(bits_in)
    if do_ffc:
        ar = np.float64(a[r, c])
        br = np.float64(b[r, c])
        k, flags, _ = invert_point(y, t, ar, br, d, full_scale, np.inf, tol_dn, max_iter)
        am = alpha_model_point(y, max(k, 1e-300), ar, br)
        lr = np.float64(log_ratio[r, c]) if has_sweep else 0.0
        o, q, _ = correct_point(k, flags, am, y, t, d, np.float64(base[r, c]), lr, has_sweep,
                                dark_current, flat_alpha, alpha_limit, below_tol)
        out[r, c] = np.float32(o)
        bits |= q
    else:
        out[r, c] = y32 - d32
    dq_out[r, c] = np.uint32(bits)


@cuda.jit(device=True, inline=True)
def _store(cube, cube_dq, y, x, b, v, bits, mode, fold):
    if mode == 1:
        v, extra = clip_half(v)
        bits |= extra
        cube[y, x, b] = v
    elif mode == 2:
        v, extra = round_u16(v)
        bits |= extra
        cube[y, x, b] = v
    else:
        cube[y, x, b] = v
    cube_dq[y, x, b] = fold_dq8(bits) if fold else bits


@cuda.jit(device=True, inline=True)
def _wrap(d, p):
    """``d mod p`` for ``-p < d < p``, without a division."""
    return d + p if d < 0 else d


@cuda.jit(device=True, inline=True)
def _finite_alpha(a):
    """Non-finite alpha counts as the largest float32 (as :func:`hsiffc.reconstruct.demosaic`
    reads the alpha plane)."""
    return a if abs(a) < np.inf else np.float32(_F32_MAX)


def _register_capped(fn):
    """``cuda.jit`` with at most 64 registers a thread: unbounded, the rare branches of
    :data:`bilinear` (the twice-wide S2, "nearest", PPID) take registers every thread pays for
    in occupancy. The cap changes no value; it was chosen by ``benchmarks/gpu_registers.py``
    (measurements: docs/results/gpu.md). Numba's CUDA simulator takes no cap."""
    try:
        return cuda.jit(max_registers=64)(fn)
    except TypeError:
        return cuda.jit(fn)


@_register_capped
def bilinear(src, lattices, dst, fill, nearest, ppid):
    """One thread per cube value, launched as blocks of (B, pixels, rows) threads: band
    ``threadIdx.x`` of a pixel, so consecutive threads write consecutive values, and no integer
    division on the common path (64-bit integer division is slow on the GPU): the phases come
    from the tables ``ymod`` (``y % ph``) and ``xmod`` (``x % pw``), the weights from
    ``wy_of[d] = d / ph`` and ``wx_of[d] = d / pw``, the same float64 quotients.
    :mod:`hsiffc.kernels.demosaic`'s bilinear value, its DQ and (``has_alpha``) its alpha.
    Where the twice-wide support holds no usable sample either, the value is ``medians[band]``
    (``has_medians``) or NaN; both with DO_NOT_USE. Without medians, ``missing[0]`` counts such
    values and ``missing[1 + band]`` marks their bands: the caller then takes the band medians
    of the frame (:func:`hsiffc.reconstruct.prepare.band_medians`, as the CPU path) and runs
    the kernel again with them; ``miss_list`` gets the flat index ``(y W + x) B + band`` of
    each such value (while it has room), for :data:`fill_missing` to fill on the device.

    ``near``: "nearest" (:func:`hsiffc.reconstruct.demosaic`'s block replication): the value
    becomes the float32 mean of the band's usable samples in the pixel's own tile (pattern
    positions ``pat_r/pat_c``, band ``b``'s at ``pat_start[b]:pat_start[b + 1]``, tiles from
    the offset ``oy, ox``) where it has one; DQ and alpha stay bilinear's, as on the CPU.
    ``use_ppi``: PPID (:mod:`hsiffc.kernels.demosaic` with a PPI): the tent interpolates
    ``v - level ppi`` and adds ``level ppi`` back (``levels`` (B,) float64), the plain bilinear
    value (float64 sums) where the PPI is undefined, and the alpha is ``alpha_win`` (the PPI
    window's max, :data:`window_max`) in every band.

    Operands: :class:`CubeIn`, :class:`Lattices`, :class:`CubeOut`, :class:`MedianFill`,
    :class:`NearestTerms`, :class:`PpidTerms`."""
    data, dq, has_dq, alpha, has_alpha = src
    lat_r, lat_c, lat_start, ph, pw, ymod, xmod, wy_of, wx_of = lattices
    cube, cube_dq, cube_alpha, mode, fold = dst
    medians, has_medians, missing, miss_list = fill
    near, pat_r, pat_c, pat_start, oy, ox = nearest
    use_ppi, ppi, ppi_ok, levels, alpha_win = ppid
    band = cuda.threadIdx.x
    x = cuda.blockIdx.x * cuda.blockDim.y + cuda.threadIdx.y
    y = cuda.blockIdx.y * cuda.blockDim.z + cuda.threadIdx.z
    H = data.shape[0]
    W = data.shape[1]
    B = lat_start.shape[0] - 1
    if y >= H or x >= W or band >= B:
        return
    qy = ymod[y]
    qa = xmod[x]
    num = np.float32(0.0)
    den = np.float32(0.0)
    amax = _NEG
    own = np.uint32(0)
    level = levels[band] if use_ppi else 0.0
    lev = np.float32(level)  # the CPU kernel's float32 level of its lattice pass
    for j in range(lat_start[band], lat_start[band + 1]):
        dy = _wrap(qy - lat_r[j], ph)  # (y - lat_r[j]) % ph
        ry0 = y - dy
        wy1 = wy_of[dy]
        ry1 = ry0 + ph
        w0 = np.float32((1.0 - wy1) if ry0 >= 0 else 0.0)
        w1 = np.float32(wy1 if ry1 < H else 0.0)
        r0 = ry0 if ry0 >= 0 else ry1
        r1 = ry1 if ry1 < H else r0
        if r0 >= H:
            continue
        c0 = lat_c[j]
        s = 0 if qa >= c0 else 1
        p = qa - c0 + s * pw
        wr = np.float32(wx_of[p])
        wl = np.float32(1.0 - wx_of[p])
        xl = x - p
        for side in range(2):
            xs = xl + side * pw
            wx = wl if side == 0 else wr
            if xs < 0 or xs >= W or (side == 1 and p == 0):
                continue
            g0 = w0
            g1 = w1
            if has_dq:
                g0 = w0 if dq[r0, xs] == 0 else np.float32(0.0)
                g1 = w1 if dq[r1, xs] == 0 else np.float32(0.0)
            v0 = data[r0, xs]
            v1 = data[r1, xs]
            if use_ppi:  # float32, as the CPU kernel's lattice pass
                v0 = v0 - lev * ppi[r0, xs]
                v1 = v1 - lev * ppi[r1, xs]
            num += wx * (g0 * v0 + g1 * v1)
            den += wx * (g0 + g1)
            if has_alpha and not use_ppi:
                if w0 > 0.0:
                    amax = max(amax, _finite_alpha(alpha[r0, xs]))
                if w1 > 0.0:
                    amax = max(amax, _finite_alpha(alpha[r1, xs]))
        if has_dq and lat_r[j] == qy and p == 0:
            own = dq[y, x]
    bits = own
    value = np.nan
    if den > 0.0:
        v32 = num / den
        if use_ppi:
            v32 = v32 + lev * ppi[y, x]
        value = np.float64(v32)
    if use_ppi and has_dq and den > EPS and not ppi_ok[y, x]:
        value = _tent1(data, dq, y, x, lat_r, lat_c, lat_start[band], lat_start[band + 1],
                       ph, pw)  # PPI undefined: the plain bilinear value (float64 sums)
    if has_dq and not den > EPS:  # S1 holds no usable sample: S2, and S1's flags
        n2 = 0.0
        p2 = 0.0
        d2 = 0.0
        for j in range(lat_start[band], lat_start[band + 1]):
            ry0 = y - ((y - lat_r[j]) % ph)
            xs0 = x - ((x - lat_c[j]) % pw)
            for tj in range(4):  # columns: the vertical sum first, as on the CPU
                xs = xs0 + (tj - 1) * pw
                wx = max(1.0 - abs(x - xs) / (2.0 * pw), 0.0)
                if xs < 0 or xs >= W:
                    continue
                s1_col = tj == 1 or (tj == 2 and x != xs0)
                col_v = 0.0
                col_p = 0.0
                col_w = 0.0
                for ti in range(4):
                    ys = ry0 + (ti - 1) * ph
                    wy = 1.0 - abs(y - ys) / (2.0 * ph)
                    if ys < 0 or ys >= H or not wy > 0.0:
                        continue
                    f = dq[ys, xs]
                    if s1_col and (ti == 1 or (ti == 2 and y != ry0)):
                        bits |= f
                    if f == 0:
                        col_v += wy * np.float64(data[ys, xs])
                        if use_ppi:
                            col_p += wy * (np.float64(data[ys, xs])
                                           - level * np.float64(ppi[ys, xs]))
                        col_w += wy
                n2 += wx * col_v
                p2 += wx * col_p
                d2 += wx * col_w
        if d2 <= EPS:
            bits |= _DNU
            value = np.float64(medians[band]) if has_medians else np.nan
        elif use_ppi and ppi_ok[y, x]:
            value = p2 / d2 + level * np.float64(ppi[y, x])
        else:
            value = n2 / d2
    if near:  # the band's usable samples in the pixel's own tile, where it has one
        acc = np.float32(0.0)
        cnt = np.float32(0.0)
        t0y = y - _wrap(qy - oy, ph)  # oy, ox in [0, ph), [0, pw)
        t0x = x - _wrap(qa - ox, pw)
        for j in range(pat_start[band], pat_start[band + 1]):
            sy = t0y + pat_r[j]
            sx = t0x + pat_c[j]
            if sy >= 0 and sy < H and sx >= 0 and sx < W and dq[sy, sx] == 0:
                acc += data[sy, sx]
                cnt += np.float32(1.0)
        if cnt > 0.0:
            value = np.float64(acc / cnt)
    if not (value == value) and not has_medians:  # to fill with the band's median
        k = cuda.atomic.add(missing, 0, 1)
        missing[1 + band] = 1
        if k < miss_list.shape[0]:
            miss_list[k] = (y * W + x) * B + band
    _store(cube, cube_dq, y, x, band, value, np.int64(bits), mode, fold)
    if use_ppi:
        if has_alpha:
            cube_alpha[y, x, band] = alpha_win[y, x]
    elif has_alpha:
        cube_alpha[y, x, band] = amax if amax > _NEG else np.float32(0.0)


@cuda.jit(device=True, inline=True)
def _tent1(data, dq, y, x, lat_r, lat_c, j0, j1, ph, pw):
    """:func:`hsiffc.kernels.lattice.tent_sums` with ``m = 1`` (S1), its ``r / d``: the plain
    bilinear value in float64, the terms in its order."""
    H = data.shape[0]
    W = data.shape[1]
    r = 0.0
    d = 0.0
    for j in range(j0, j1):
        ry = y - ((y - lat_r[j]) % ph)
        cx = x - ((x - lat_c[j]) % pw)
        for t in range(2):
            ys = ry + t * ph
            wy = 1.0 - abs(y - ys) / ph
            if ys < 0 or ys >= H or wy <= 0.0:
                continue
            for u in range(2):
                xs = cx + u * pw
                wx = 1.0 - abs(x - xs) / pw
                if xs < 0 or xs >= W or wx <= 0.0:
                    continue
                if dq[ys, xs] == 0:
                    w = wy * wx
                    r += w * np.float64(data[ys, xs])
                    d += w
    return r / d


@cuda.jit
def fill_missing(missing, miss_list, medians, mode, cube, cube_dq):
    """The values :data:`bilinear` listed (no usable sample within twice the tile): the band's
    median (:data:`median_mean`), stored in the stream's output type with what storing it
    flags (bits 0-7 only, so a folded uint8 DQ takes them as they are). A grid-stride loop:
    nothing to do costs one read per block."""
    n = min(missing[0], miss_list.shape[0])
    B = cube.shape[2]
    W = cube.shape[1]
    start, step = cuda.grid(1), cuda.gridsize(1)
    for i in range(start, n, step):
        code = miss_list[i]
        band = code % B
        px = code // B
        y = px // W
        x = px - y * W
        v = np.float64(medians[band])
        extra = 0
        if mode == 1:
            v, extra = clip_half(v)
        elif mode == 2:
            v, extra = round_u16(v)
        cube[y, x, band] = v
        if extra != 0:
            cube_dq[y, x, band] |= extra


@cuda.jit
def flag_uncertain(frame, dq, c, e, bit):
    """``bit`` into ``dq`` where ``c > e frame^2`` (float32): the model FFC's UNCERTAIN flag,
    as :func:`hsiffc.kernels.bits.or_into_flag_uncertain` sets it on the CPU."""
    x, r = cuda.grid(2)
    if r < frame.shape[0] and x < frame.shape[1]:
        v = frame[r, x]
        if c[r, x] > e[r, x] * v * v:
            dq[r, x] |= bit


@cuda.jit
def pack2d(frame, dq, mode, fold, out, out_dq):
    """A corrected frame (float32, uint32 DQ) into the stream's output types."""
    c, r = cuda.grid(2)
    if r < frame.shape[0] and c < frame.shape[1]:
        _store2(out, out_dq, r, c, np.float64(frame[r, c]), np.int64(dq[r, c]), mode, fold)


@cuda.jit(device=True, inline=True)
def _store2(out, out_dq, r, c, v, bits, mode, fold):
    if mode == 1:
        v, extra = clip_half(v)
        bits |= extra
    elif mode == 2:
        v, extra = round_u16(v)
        bits |= extra
    out[r, c] = v
    out_dq[r, c] = fold_dq8(bits) if fold else bits


# -- band medians (the fill of values with no usable sample), exact, on the device -------------
# The median of a band's usable samples as numpy's partition gives it (the CPU path's
# hsiffc.reconstruct.prepare.band_medians): the order statistics of rank n // 2 (and n // 2 - 1
# for an even count, averaged in float32) found by a radix select over the float32 bit
# patterns made order-preserving (sign flipped for positives, all bits for negatives), four
# bits per pass, eight passes, with no round trip to the host. Up to MAX_BANDS bands (the
# block-local histograms live in shared memory).
_RANKS = 2
_BINS = 16
MAX_BANDS = 32
DIGIT_SHIFTS = tuple(range(28, -1, -4))


@cuda.jit(device=True, inline=True)
def _key(bits):
    """Order-preserving key of a float32's bits (as uint32)."""
    return bits ^ (np.uint32(0xFFFFFFFF) if (bits >> np.uint32(31)) != 0
                   else np.uint32(0x80000000))


@cuda.jit
def median_hist(bits, dq, phase_band, ph, pw, prefix, mask, shift, first, hist, need):
    """Per band and rank, the histogram of the next 4 key bits of the usable samples whose
    higher bits equal the rank's ``prefix`` (``mask``: the bits known; every sample on the
    ``first`` pass), block-local first. Nothing is done unless ``need[0]`` (the count of
    values to fill, or 1 where the medians are always needed: PPID's band levels), so the
    exact medians cost a bilinear cube only on the frames that use them. Rows in a
    grid-stride loop: a block flushes its histogram once for many rows."""
    if need[0] == 0:
        return
    local = cuda.shared.array(shape=(MAX_BANDS, _RANKS, _BINS), dtype=np.int32)
    tid = cuda.threadIdx.x + cuda.threadIdx.y * cuda.blockDim.x
    nthreads = cuda.blockDim.x * cuda.blockDim.y
    B = hist.shape[0]
    for t in range(tid, B * _RANKS * _BINS, nthreads):
        local[t // (_RANKS * _BINS), (t // _BINS) % _RANKS, t % _BINS] = 0
    cuda.syncthreads()
    x, y0 = cuda.grid(2)
    ystep = cuda.gridDim.y * cuda.blockDim.y
    if x < bits.shape[1]:
        for y in range(y0, bits.shape[0], ystep):
            if dq[y, x] != 0:
                continue
            band = phase_band[(y % ph) * pw + (x % pw)]
            if band >= 0:
                key = _key(bits[y, x])
                digit = (key >> shift) & np.uint32(0xF)
                if first or prefix[band, 0] == prefix[band, 1]:  # one histogram for both
                    if first or (key & mask) == prefix[band, 0]:  # ranks while they agree
                        cuda.atomic.add(local, (band, 0, digit), 1)
                else:
                    for r in range(_RANKS):
                        if (key & mask) == prefix[band, r]:
                            cuda.atomic.add(local, (band, r, digit), 1)
    cuda.syncthreads()
    for t in range(tid, B * _RANKS * _BINS, nthreads):
        b = t // (_RANKS * _BINS)
        r = (t // _BINS) % _RANKS
        v = local[b, r, t % _BINS]
        if v != 0:
            cuda.atomic.add(hist, (b, r, t % _BINS), v)


@cuda.jit
def median_select(hist, prefix, rank, count, shift, first):
    """One thread per (band, rank): the bin holding the rank (the count and the ranks set on
    the first pass), appended to the prefix; the histogram zeroed for the next pass. While
    the two ranks' prefixes agree (always for an odd count, and on the first passes)
    :data:`median_hist` fills one histogram, row 0, for both (half the atomic adds)."""
    b = cuda.blockIdx.x
    r = cuda.threadIdx.x
    active = b < hist.shape[0] and r < _RANKS
    same = True
    if active:
        same = first or prefix[b, 0] == prefix[b, 1]
    cuda.syncthreads()  # both threads read the prefixes before either changes its own
    if active:
        src = 0 if same else r
        if first:  # every sample in the histogram: each thread counts it
            n = 0
            for i in range(_BINS):
                n += hist[b, src, i]
            if r == 0:
                count[b] = n
            rank[b, r] = n // 2 - 1 if (r == 0 and n % 2 == 0) else n // 2
            prefix[b, r] = 0
        k = rank[b, r]
        for i in range(_BINS):
            c = hist[b, src, i]
            if k >= 0 and k < c:
                prefix[b, r] |= np.uint32(i) << shift
                rank[b, r] = k
                k = -1
            elif k >= 0:
                k -= c
    cuda.syncthreads()  # both have read row 0 before it is zeroed
    if active:
        for i in range(_BINS):
            hist[b, r, i] = 0


@cuda.jit
def median_finish(prefix, count, out_bits):
    """The keys found back to float32 bits (read as float32 by :data:`median_mean`)."""
    b = cuda.grid(1)
    if b < prefix.shape[0]:
        for r in range(_RANKS):
            key = prefix[b, r]
            out_bits[b, r] = key ^ (np.uint32(0x80000000) if (key >> np.uint32(31)) != 0
                                    else np.uint32(0xFFFFFFFF))


@cuda.jit
def median_mean(values, count, medians):
    """Median of each band: the middle value, the float32 mean of the two middle values for
    an even count, 0 for a band with no usable sample."""
    b = cuda.grid(1)
    if b < medians.shape[0]:
        n = count[b]
        if n == 0:
            medians[b] = 0.0
        elif n % 2:
            medians[b] = values[b, 1]
        else:
            medians[b] = np.float32(values[b, 0] + values[b, 1]) / np.float32(2.0)


@cuda.jit
def correction_matrix(cube, cube_dq, cube_alpha, has_alpha, coef, support, mode, fold, out,
                      out_dq, out_alpha):
    """The spectral correction matrix per pixel (:func:`hsiffc.reconstruct.apply_correction`),
    one thread per virtual value (blocks of (V, pixels, rows) threads): ``sum_b coef[b, v]
    cube[b]`` in float32 (``coef`` the matrix transposed, as the CPU's float32 product takes
    it; the sum's order differs from BLAS's, so the value agrees within float32 rounding of
    the terms), the OR of the DQ and the max of the alpha of the bands in the row's
    ``support`` (0 where it has none), stored in the stream's output types."""
    v = cuda.threadIdx.x  # blocks of (V, pixels, rows) threads, as :data:`bilinear`
    x = cuda.blockIdx.x * cuda.blockDim.y + cuda.threadIdx.y
    y = cuda.blockIdx.y * cuda.blockDim.z + cuda.threadIdx.z
    H = cube.shape[0]
    W = cube.shape[1]
    B = cube.shape[2]
    V = coef.shape[1]
    if y >= H or x >= W or v >= V:
        return
    acc = np.float32(0.0)
    bits = np.uint32(0)
    amax = _NEG
    for b in range(B):
        acc += cube[y, x, b] * coef[b, v]
        if support[b, v]:
            bits |= cube_dq[y, x, b]
            if has_alpha:
                amax = max(amax, cube_alpha[y, x, b])
    _store(out, out_dq, y, x, v, np.float64(acc), np.int64(bits), mode, fold)
    if has_alpha:
        out_alpha[y, x, v] = amax if amax > _NEG else np.float32(0.0)


# -- PPID: band levels, the pseudo-panchromatic image, the alpha window -----------------------
@cuda.jit
def band_levels(medians, levels, inv_level):
    """:func:`hsiffc.reconstruct.prepare.band_levels` from the band medians (one thread): each
    median over their mean (numpy's pairwise sum of up to 128 values, in its order), or all
    ones where a median is not positive or not finite; ``inv_level`` the float32 of
    ``1 / level`` (:func:`~hsiffc.reconstruct.prepare.pseudo_panchromatic`)."""
    if cuda.grid(1) != 0:
        return
    n = medians.shape[0]
    ok = True
    for b in range(n):
        m = np.float64(medians[b])
        if not (abs(m) < np.inf) or not m > 0.0:
            ok = False
    if n < 8:
        total = -0.0
        for b in range(n):
            total += np.float64(medians[b])
    else:  # numpy's blocked pairwise sum (n <= 128: one block of eight accumulators)
        r0 = np.float64(medians[0])
        r1 = np.float64(medians[1])
        r2 = np.float64(medians[2])
        r3 = np.float64(medians[3])
        r4 = np.float64(medians[4])
        r5 = np.float64(medians[5])
        r6 = np.float64(medians[6])
        r7 = np.float64(medians[7])
        i = 8
        while i < n - (n % 8):
            r0 += np.float64(medians[i])
            r1 += np.float64(medians[i + 1])
            r2 += np.float64(medians[i + 2])
            r3 += np.float64(medians[i + 3])
            r4 += np.float64(medians[i + 4])
            r5 += np.float64(medians[i + 5])
            r6 += np.float64(medians[i + 6])
            r7 += np.float64(medians[i + 7])
            i += 8
        total = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
        while i < n:
            total += np.float64(medians[i])
            i += 1
    mean = total / n
    for b in range(n):
        lv = np.float64(medians[b]) / mean if ok else 1.0
        levels[b] = lv
        inv_level[b] = np.float32(1.0 / lv)


@cuda.jit
def ppi_values(data, dq, band_of, inv_level, vals, wts):
    """The PPI's input (:func:`hsiffc.kernels.ppi._ppi_rows`, first pass): each sample over
    its band's level (float32); a flagged one as the tent-weighted mean of its usable
    same-band neighbours one tile away (1/4 diagonal, 1/2 straight, float64, in
    :func:`~hsiffc.kernels.ppi.neighbour_offsets`' order) over its level, weight 0 where it
    has none."""
    x, y = cuda.grid(2)
    H = data.shape[0]
    W = data.shape[1]
    if y >= H or x >= W:
        return
    ph = band_of.shape[0]
    pw = band_of.shape[1]
    inv = inv_level[band_of[y % ph, x % pw]]
    if dq[y, x] == 0:
        vals[y, x] = data[y, x] * inv
        wts[y, x] = np.float32(1.0)
        return
    acc = 0.0
    wsum = 0.0
    for ty in range(3):
        for tx in range(3):
            if ty == 1 and tx == 1:
                continue
            dy = (ty - 1) * ph
            dx = (tx - 1) * pw
            ny = y + dy
            nx = x + dx
            if ny < 0 or ny >= H or nx < 0 or nx >= W:
                continue
            g = (0.25 if (dy != 0 and dx != 0) else 0.5) if dq[ny, nx] == 0 else 0.0
            acc += g * np.float64(data[ny, nx])
            wsum += g
    if wsum > 0.0:
        vals[y, x] = np.float32(acc / wsum) * inv
        wts[y, x] = np.float32(1.0)
    else:
        vals[y, x] = np.float32(0.0)
        wts[y, x] = np.float32(0.0)


@cuda.jit
def ppi_window(vals, wts, rows, cols, kx, ky, ppi, ok):
    """The PPI (:func:`hsiffc.kernels.ppi._window_block`): the separable window sums of
    ``vals`` and ``wts`` (float64, each in the order of a loop over its taps; rows and columns
    beyond the frame mapped back by whole tiles through ``rows``/``cols``), their ratio where
    the weight exceeds 1e-6 (``ok``), else 0."""
    x, y = cuda.grid(2)
    if y >= ppi.shape[0] or x >= ppi.shape[1]:
        return
    n = 0.0
    d = 0.0
    for ty in range(ky.shape[0]):
        r = rows[y + ty]
        hn = 0.0
        hd = 0.0
        for tx in range(kx.shape[0]):
            c = cols[x + tx]
            hn += kx[tx] * np.float64(vals[r, c])
            hd += kx[tx] * np.float64(wts[r, c])
        n += ky[ty] * hn
        d += ky[ty] * hd
    good = d > 1e-6
    ppi[y, x] = np.float32(n / d) if good else np.float32(0.0)
    ok[y, x] = 1 if good else 0


@cuda.jit
def window_max(alpha, my, mx, out):
    """The max of ``alpha`` over the ``(2 my + 1) x (2 mx + 1)`` window centred on each
    pixel, edges replicated (``cv2.dilate`` with ``BORDER_REPLICATE``: PPID's alpha); a
    non-finite alpha counts as the largest float32."""
    x, y = cuda.grid(2)
    H = alpha.shape[0]
    W = alpha.shape[1]
    if y >= H or x >= W:
        return
    m = _NEG
    for yy in range(y - my, y + my + 1):
        r = min(max(yy, 0), H - 1)
        for xx in range(x - mx, x + mx + 1):
            c = min(max(xx, 0), W - 1)
            m = max(m, _finite_alpha(alpha[r, c]))
    out[y, x] = m


# -- two-point FFC (eq. 5) ----------------------------------------------------------------------
@cuda.jit
def band_sums(raw, dq, band, sums, counts):
    """Per band, the sum (float64) and count of the raw values ``float32(raw)`` of the pixels
    whose DQ is 0: the test level ``Avg(L3)`` of eq. (5), as
    :func:`hsiffc.leakage.validity.subtract_dark_and_flag` takes it (sums of integer DN are
    exact in any order). Block-local sums first, one atomic add per block and band."""
    s_sum = cuda.shared.array(MAX_BANDS, dtype=np.float64)
    s_cnt = cuda.shared.array(MAX_BANDS, dtype=np.int64)
    tid = cuda.threadIdx.x + cuda.threadIdx.y * cuda.blockDim.x
    nthreads = cuda.blockDim.x * cuda.blockDim.y
    B = sums.shape[0]
    for t in range(tid, B, nthreads):
        s_sum[t] = 0.0
        s_cnt[t] = 0
    cuda.syncthreads()
    x, y0 = cuda.grid(2)
    ystep = cuda.gridDim.y * cuda.blockDim.y
    if x < raw.shape[1]:
        for y in range(y0, raw.shape[0], ystep):
            if dq[y, x] == 0:
                b = band[y, x]
                cuda.atomic.add(s_sum, b, np.float64(np.float32(raw[y, x])))
                cuda.atomic.add(s_cnt, b, 1)
    cuda.syncthreads()
    for t in range(tid, B, nthreads):
        if s_cnt[t] != 0:
            cuda.atomic.add(sums, t, s_sum[t])
            cuda.atomic.add(counts, t, s_cnt[t])


@cuda.jit
def two_point_ratio(sums, counts, flat_mean, ratio):
    """Eq. (5)'s factor per band (:func:`hsiffc.flatfield.two_point.means_ratio`): the test
    level over the flat's mean, float32; 1 where it is not a positive finite number."""
    b = cuda.grid(1)
    if b < ratio.shape[0]:
        n = counts[b]
        mean = sums[b] / n if n > 0 else np.nan
        r = mean / flat_mean[b]
        ratio[b] = np.float32(r) if (abs(r) < np.inf and r > 0.0) else np.float32(1.0)


@cuda.jit
def two_point_apply(frame, dq, gain, ratio, band):
    """``frame = signal * gain * ratio[band]`` in place (float64 products stored as float32,
    :func:`hsiffc.flatfield.two_point.two_point_apply`); a product that is not finite is
    stored as 0 with NONFINITE | DO_NOT_USE."""
    x, y = cuda.grid(2)
    if y < frame.shape[0] and x < frame.shape[1]:
        o = np.float32(np.float64(frame[y, x]) * np.float64(gain[y, x])
                       * np.float64(ratio[band[y, x]]))
        if abs(o) < np.inf:
            frame[y, x] = o
        else:
            frame[y, x] = np.float32(0.0)
            dq[y, x] |= _BAD_INPUT
