"""EMVA 1288 step statistics reduced while the frames are read: memory bounded by a few frames.

Every frame goes once through a kernel (numba, compiled, without the GIL) that adds it to
its step's accumulators; a step is reduced to its statistics when its last frame has been read,
and the frames are never held together. Per pixel the kernel keeps the step's first frame
``f0`` and the sums ``S1 = sum (f - f0)`` and ``S2 = sum (f - f0)^2`` over the later frames
(exact in float64 for integer DN), so the per-pixel temporal variance
``(S2 - S1^2 / L) / (L - 1)`` does not lose digits to a large mean. Per frame it also sums
each pixel group (the whole frame, each band of a mosaic), and counts the pixels at full scale.

What a step gives, per pixel group:

- its mean ``u_y`` (DN), the mean of the frames' group means;
- its temporal variance (DN^2) as Release 4.0 defines it: the per-pixel variance over the
  frames of each frame less its own group mean, averaged over the pixels. It equals the mean of
  the per-pixel variances less the variance of the frames' group means (the cross term of the
  two averages is that variance), which is what is computed; with two frames it is the
  standard's ``1/(2N) sum ((A - B) - mean(A - B))^2``;
- the share of pixels at full scale in some frame of the step.

A spatial stack (one light and one dark step of many frames) keeps its sum image and its
per-pixel temporal variance image (DN^2) for the nonuniformity figures, the defect-pixel
histograms and the spectrograms (:mod:`.spatial`). With ``keep_step_means`` every step's
per-pixel mean image (float32) is kept for the leakage calibration, with a pixel set to full
scale where some frame of its step was (so the calibration sees it clipped), and the first
two frames of each step give the calibration's photon transfer (pixels below full scale in
both: their number, mean level and half the mean squared difference).

The frames are read by :class:`hsiffc.io.FrameSource`, which decodes the next frames on worker
threads while the kernel works on the current one: both cores are busy (decoding a frame
costs several times what the kernel does). The kernel runs compiled (numba, one pass, no
temporaries) from :data:`COMPILED_FROM` pixel-frames on, and as whole-array numpy below,
where loading numba's code generator would cost more than the compiled pass saves; the two
give the same statistics (tests/emva1288/test_emva_release4.py).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from ..data.mosaic import mosaic_band_labels
from ..errors import DataFormatError

__all__ = ["reduce_frames", "SPATIAL_FACTOR"]

SPATIAL_FACTOR = 2.0  # a step with more than this x the median frames per step is a spatial stack


def _add_frame(v, j, first, s1, s2, clip, band, n_bands, fs, pairs):
    """Add frame number ``j`` of a step (``v``: the frame flattened, float64 DN) to its
    accumulators (flat, in place); return the frame's sum per group (whole frame, then each
    of ``n_bands`` bands by ``band``). ``pairs`` (3,) gathers the first two frames' pixels
    below full scale in both: count, sum of their means, sum of squared differences.
    Whole-array numpy; :func:`_add_frame_compiled` is the same in one compiled pass."""
    sums = np.zeros(1 + n_bands)
    sums[0] = v.sum()
    if n_bands > 0:
        sums[1:] = np.bincount(band, v, n_bands)
    at = v >= fs
    if j == 0:
        first[:] = v
        s1[:] = 0.0
        s2[:] = 0.0
        clip[:] = at
    else:
        d = v - first
        s1 += d
        d2 = d * d
        s2 += d2
        clip |= at
        if j == 1:
            ok = (first < fs) & ~at
            pairs[0] += ok.sum()
            pairs[1] += 0.5 * (first[ok].sum() + v[ok].sum())
            pairs[2] += d2[ok].sum()
    return sums


@njit(cache=True, nogil=True)
def _add_frame_compiled(frame, j, first, s1, s2, clip, band, n_bands, fs, pairs):
    """:func:`_add_frame` as one pass over the pixels (``frame`` flat, any integer or float
    dtype): no temporaries, 0.54 ms against 2.7 ms of CPU per 512 x 512 frame here."""
    sums = np.zeros(1 + n_bands)
    for i in range(frame.size):
        v = np.float64(frame[i])
        sums[0] += v
        if n_bands > 0:
            sums[band[i] + 1] += v
        at = v >= fs
        if j == 0:
            first[i] = v
            s1[i] = 0.0
            s2[i] = 0.0
            clip[i] = at
        else:
            a = first[i]
            d = v - a
            s1[i] += d
            s2[i] += d * d
            clip[i] |= at
            if j == 1 and a < fs and not at:
                pairs[0] += 1.0
                pairs[1] += 0.5 * (a + v)
                pairs[2] += d * d
    return sums


def _finish_step(first, s1, s2, clip, n, band, n_bands, fs, want_mean, want_images):
    """Reduce a step of ``n`` frames: the sum of the per-pixel temporal variances per group,
    the number of pixels at full scale in some frame, and (else empty) the mean image
    (float32, full scale where clipped), the sum image and the variance image (float64)."""
    inv = 1.0 / n
    if n > 1:
        var = (s2 - s1 * s1 * inv) / (n - 1)
    else:
        var = np.zeros_like(s1)
    vs = np.zeros(1 + n_bands)
    vs[0] = var.sum()
    if n_bands > 0:
        vs[1:] = np.bincount(band, var, n_bands)
    mean = np.empty(0, np.float32)
    if want_mean:
        mean = np.where(clip, fs, first + s1 * inv).astype(np.float32)
    total = np.empty(0)
    if want_images:
        total = first * n + s1
    else:
        var = np.empty(0)
    return vs, float(clip.sum()), mean, total, var


#: pixels x frames from which the compiled kernel runs: its first call loads numba's code
#: generator, 0.94 s of CPU and 60 MB resident here (a 1024 x 1024 set: 295 MB against 235 MB
#: with numpy, the reference 173 MB), which it earns back at about 8 ns per pixel-frame
#: (0.54 ms against numpy's 2.7 ms per 512 x 512 frame): 1e8 pixel-frames for the time, and
#: from 5e8 on the 60 MB are small beside the frames; below, numpy
COMPILED_FROM = 5e8


class _StepState:
    """Accumulators of the step being read (buffers reused from step to step)."""

    def __init__(self, n_pixels):
        self.first = np.empty(n_pixels)
        self.s1 = np.empty(n_pixels)
        self.s2 = np.empty(n_pixels)
        self.clip = np.empty(n_pixels, np.bool_)
        self.reset(None, None)

    def reset(self, step, meta):
        self.step, self.meta, self.n = step, meta, 0
        self.frame_sums: list = []
        self.pairs = np.zeros(3)


def _frames_of(source):
    """(frame, step id, kind, exposure_ms, photons) in order, from a Sweep (step by step) or a
    FrameSource (as read)."""
    if hasattr(source, "data"):
        for s in source.steps():
            for i in np.flatnonzero(source.step == s):
                yield (source.data[i], int(s), str(source.kind[i]),
                       float(source.exposure_ms[i]), float(source.photons[i]))
        return
    for raw, m in source:
        yield raw, m.step, m.kind, m.exposure_ms, m.photons


def _group_map(source, frame_shape, mosaic_bands):
    """(band index of every pixel, flat int64; or empty without bands) and the band count."""
    mosaic = getattr(source, "mosaic", None)
    if mosaic_bands and mosaic is not None:
        return mosaic.band_map(frame_shape).astype(np.int64).ravel(), int(mosaic.n_bands)
    return np.empty(0, np.int64), 0


def reduce_frames(source, *, mosaic_bands: bool = True, keep_step_means: bool = False,
                  spatial_steps=None) -> dict:
    """Reduce a measurement to its EMVA 1288 step statistics, one frame at a time.

    Parameters
    ----------
    source : Sweep or FrameSource
        An EMVA 1288 measurement in memory (:func:`hsiffc.io.read_emva1288`) or opened for
        streaming (:func:`hsiffc.io.open_source` on its descriptor): light steps with photon
        counts, dark steps, optionally a spatial stack. A FrameSource must give the frames of
        each step one after the other (EMVA 1288 descriptors do).
    mosaic_bands : bool
        Also per band when the measurement has a mosaic.
    keep_step_means : bool
        Keep every step's per-pixel mean image and the pair statistics (for the leakage
        calibration).
    spatial_steps : sequence of int, optional
        The steps of the spatial stack (default: ``meta["spatial_steps"]``, else the steps with
        more than twice the median number of frames).

    Returns
    -------
    dict
        ``steps`` (per-step arrays ``step``, ``kind``, ``exposure_ms``, ``photons``,
        ``n_frames``, ``spatial``, ``clipped_share``), ``groups`` (per group: ``label``,
        ``band``, ``n_pixels``, ``mean_dn`` and ``var_dn2`` per step), ``images`` (the spatial
        stacks' ``sum`` and ``var`` images and frame counts, by kind, or None),
        ``frame_shape``, ``n_pixels``, ``bit_depth``, ``full_scale_dn``; with
        ``keep_step_means`` also ``step_means`` (S, H, W) float32 and ``pairs`` (S, 3).

    Raises
    ------
    DataFormatError
        A step whose frames are not contiguous in the stream.
    """
    meta = getattr(source, "meta", {}) or {}
    frame_shape = tuple(source.frame_shape)
    bit_depth = int(source.bit_depth)
    fs = float(2 ** bit_depth - 1)
    where = getattr(source, "source", None) or getattr(source, "label", None) or None
    band, n_bands = _group_map(source, frame_shape, mosaic_bands)
    n_groups = 1 + n_bands
    n_total = int(np.prod(frame_shape))
    n_pix = np.concatenate([[n_total], np.bincount(band, minlength=n_bands)[:n_bands]]
                           ).astype(np.float64)
    if spatial_steps is None:
        spatial_steps = meta.get("spatial_steps")
    if spatial_steps is None:
        steps_all = np.asarray(source.step)
        ids, cnt = np.unique(steps_all, return_counts=True)
        spatial_steps = ids[cnt > SPATIAL_FACTOR * np.median(cnt)].tolist()
    spatial = {int(s) for s in spatial_steps}
    compiled = float(source.n_frames) * n_total >= COMPILED_FROM
    reduce_step = _finish_step
    st = _StepState(n_total)
    rows: list[dict] = []
    images: dict = {}
    means: list = []
    done: set = set()

    def finish():
        if st.step is None:
            return
        is_sp = st.step in spatial
        vs, n_clip, mean_img, sum_img, var_img = reduce_step(
            st.first, st.s1, st.s2, st.clip, st.n, band, n_bands, fs,
            keep_step_means and not is_sp, is_sp)
        fm = np.array(st.frame_sums) / n_pix  # (L, G) frame means per group
        mean = fm.mean(axis=0)
        var = (vs / n_pix - fm.var(axis=0, ddof=1)) if st.n > 1 else np.full(n_groups, np.nan)
        kind, exposure, photons = st.meta
        rows.append({"step": st.step, "kind": kind, "exposure_ms": exposure,
                     "photons": photons, "n_frames": st.n, "spatial": is_sp,
                     "clipped_share": n_clip / n_total, "mean": mean, "var": var,
                     "pairs": st.pairs.copy()})
        if is_sp:
            images.setdefault(kind, []).append({"sum": sum_img.reshape(frame_shape),
                                                "var": var_img.reshape(frame_shape),
                                                "L": st.n, "step": st.step})
        elif keep_step_means:
            means.append((st.step, mean_img.reshape(frame_shape)))
        done.add(st.step)

    for frame, step, kind, exposure, photons in _frames_of(source):
        if step != st.step:
            finish()
            if step in done:
                raise DataFormatError(f"the frames of step {step} are not one after the other; "
                                      "EMVA 1288 lists each step's images together: fix the "
                                      "descriptor's order", path=where)
            st.reset(step, (kind, exposure, photons))
        if compiled:
            sums = _add_frame_compiled(np.ascontiguousarray(frame).reshape(-1), st.n, st.first,
                                       st.s1, st.s2, st.clip, band, n_bands, fs, st.pairs)
        else:
            sums = _add_frame(np.asarray(frame, np.float64).reshape(-1), st.n, st.first, st.s1,
                              st.s2, st.clip, band, n_bands, fs, st.pairs)
        st.frame_sums.append(sums)
        st.n += 1
    finish()
    order = np.argsort([r["step"] for r in rows], kind="stable")
    rows = [rows[i] for i in order]
    info = {"step": np.array([r["step"] for r in rows], int),
            "kind": np.array([r["kind"] for r in rows], dtype=object),
            "exposure_ms": np.array([r["exposure_ms"] for r in rows], np.float64),
            "photons": np.array([r["photons"] for r in rows], np.float64),
            "n_frames": np.array([r["n_frames"] for r in rows]),
            "spatial": np.array([r["spatial"] for r in rows]),
            "clipped_share": np.array([r["clipped_share"] for r in rows])}
    labels = ["all pixels"] + (mosaic_band_labels(getattr(source, "mosaic", None), n_bands)
                               if n_bands else [])
    groups = [{"label": labels[g], "band": None if g == 0 else g - 1,
               "n_pixels": int(n_pix[g]),
               "mean_dn": np.array([r["mean"][g] for r in rows]),
               "var_dn2": np.array([np.nan if r["spatial"] else r["var"][g] for r in rows])}
              for g in range(n_groups)]
    out = {"steps": info, "groups": groups, "frame_shape": list(frame_shape),
           "n_pixels": n_total, "bit_depth": bit_depth, "full_scale_dn": int(fs),
           "band_map": band if n_bands else None, "images": None}
    light, dark = images.get("light", []), images.get("dark", [])
    if len(light) == 1 and len(dark) == 1:
        out["images"] = {"light": light[0], "dark": dark[0]}
    out["spatial_counts"] = (len(light), len(dark))
    if keep_step_means:
        sweep_rows = [r for r in rows if not r["spatial"]]
        means.sort(key=lambda m: m[0])  # in step order, as the rows
        out["step_means"] = (np.stack([m for _, m in means]) if means else
                             np.empty((0,) + frame_shape, np.float32))
        out["sweep_step_info"] = {k: np.array([r[k] for r in sweep_rows]) for k in
                                  ("step", "kind", "exposure_ms", "photons", "n_frames")}
        out["pairs"] = np.array([r["pairs"] for r in sweep_rows])
    return out
