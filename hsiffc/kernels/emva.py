"""The compiled form of :mod:`hsiffc.emva1288.stream`'s step reduction (numba, without the GIL): one pass over
a frame in its own dtype, no temporaries, no float64 copy of the frame. One thread: the other
core decodes the next frames meanwhile (:class:`hsiffc.io.FrameSource` reads ahead on worker
threads), and numba's parallel loops spin-wait for their threads, which on two cores shared with
other work cost more CPU than they save (25 ms against 4 ms of CPU per 1024 x 1024 frame
here). Imported only when :mod:`.stream` runs compiled, so that a small set never loads numba's
code generator. The numpy form (:func:`hsiffc.emva1288.stream._add_frame`,
:func:`hsiffc.emva1288.stream._finish_step`) gives the same statistics (the two are compared in
tests/emva1288/test_emva_release4.py).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from .launch import cached_jit

__all__ = ["add_frame", "finish_step"]

#: pixels per partial sum (the partial sums are added at the end: fewer digits lost than in one
#: running sum over millions of pixels)
CHUNK = 1 << 16


@njit(cache=False, nogil=True)  # compiled into its callers
def _chunks(n):
    return max(1, (n + CHUNK - 1) // CHUNK)


@cached_jit(nogil=True)
def add_frame(frame, j, first, s1, s2, clip, band, n_bands, fs, pairs):
    """Add frame number ``j`` of a step (``frame`` flat, any integer or float dtype) to the
    step's accumulators (flat, in place: ``first`` the step's first frame, ``s1`` and ``s2``
    the sums of the later frames' differences from it and of their squares, ``clip`` whether
    the pixel was at full scale ``fs`` in some frame); ``pairs`` (3,) gathers the first two
    frames' pixels below full scale in both (count, sum of their means, sum of squared
    differences). Returns the frame's sum per group (whole frame, then each of ``n_bands``
    bands by ``band``)."""
    n = frame.size
    g = 1 + n_bands
    nch = _chunks(n)
    part = np.zeros((nch, g + 3))
    for c in range(nch):
        lo = c * CHUNK
        hi = min(n, lo + CHUNK)
        tot = 0.0
        pc = 0.0
        pm = 0.0
        pd = 0.0
        if j == 0:
            for i in range(lo, hi):
                v = np.float64(frame[i])
                tot += v
                if n_bands > 0:
                    part[c, band[i] + 1] += v
                first[i] = v
                s1[i] = 0.0
                s2[i] = 0.0
                clip[i] = v >= fs
        else:
            for i in range(lo, hi):
                v = np.float64(frame[i])
                tot += v
                if n_bands > 0:
                    part[c, band[i] + 1] += v
                a = np.float64(first[i])
                d = v - a
                s1[i] += d
                s2[i] += d * d
                at = v >= fs
                if at:
                    clip[i] = True
                if j == 1 and a < fs and not at:
                    pc += 1.0
                    pm += 0.5 * (a + v)
                    pd += d * d
        part[c, 0] = tot
        part[c, g] = pc
        part[c, g + 1] = pm
        part[c, g + 2] = pd
    sums = np.zeros(g)
    for c in range(nch):
        for k in range(g):
            sums[k] += part[c, k]
        for k in range(3):
            pairs[k] += part[c, g + k]
    return sums


@cached_jit(nogil=True)
def finish_step(first, s1, s2, clip, n, band, n_bands, fs, mean, total):
    """Reduce a step of ``n`` frames from its accumulators: returns the sum of the per-pixel
    temporal variances ``(s2 - s1^2 / n) / (n - 1)`` per group and, last, the number of
    pixels at full scale in some frame. Fills ``mean`` (float32, full scale where clipped)
    and ``total`` (the sum image) unless they are empty."""
    size = s1.size
    g = 1 + n_bands
    nch = _chunks(size)
    part = np.zeros((nch, g + 1))
    inv = 1.0 / n
    want_mean = mean.size > 0
    want_sum = total.size > 0
    for c in range(nch):
        lo = c * CHUNK
        hi = min(size, lo + CHUNK)
        tot = 0.0
        nclip = 0.0
        for i in range(lo, hi):
            a = s1[i]
            w = (s2[i] - a * a * inv) / (n - 1) if n > 1 else 0.0
            tot += w
            if n_bands > 0:
                part[c, band[i] + 1] += w
            if clip[i]:
                nclip += 1.0
            if want_mean:
                mean[i] = fs if clip[i] else first[i] + a * inv
            if want_sum:
                total[i] = first[i] * n + a
        part[c, 0] = tot
        part[c, g] = nclip
    out = np.zeros(g + 1)
    for c in range(nch):
        for k in range(g + 1):
            out[k] += part[c, k]
    return out
