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

A spatial stack (one light and one dark step of many frames) keeps its sum image and its mean
temporal variance per group (DN^2) for the nonuniformity figures, the defect-pixel histograms
and the spectrograms (:mod:`.spatial`). With ``keep_step_means`` every step's per-pixel mean
image (float32; or its values at given pixels) is kept for the leakage calibration, with a
pixel set to full scale where some frame of its step was (so the calibration sees it clipped),
and the first two frames of each step give the calibration's photon transfer (pixels below full
scale in both: their number, mean level and half the mean squared difference).

The frames are read by :class:`hsiffc.io.FrameSource`, which decodes the next frames on worker
threads while the kernel works on the current one: both cores are busy (decoding a frame
costs several times what the kernel does). The kernel runs as whole-array numpy, or compiled
(:mod:`hsiffc.kernels.emva`: numba, one pass over the frame in its own dtype, no temporaries) for very
large frames in large sets (:data:`COMPILED_FRAME_PIXELS`, :data:`COMPILED_FROM`), where
numpy's temporaries would outweigh the memory of numba's code generator (a smaller set never
loads numba); the two give the same statistics (tests/emva1288/test_emva_release4.py).
A step's first frame is held as float32 where that is exact (integer frames of up to 16 bits).
"""

from __future__ import annotations

import numpy as np

from ..data.mosaic import mosaic_band_labels
from ..errors import DataFormatError

__all__ = ["reduce_frames", "SPATIAL_FACTOR"]

SPATIAL_FACTOR = 2.0  # a step with more than this x the median frames per step is a spatial stack


def _add_frame(frame, j, first, s1, s2, clip, band, n_bands, fs, pairs):
    """Add frame number ``j`` of a step (``frame`` flat, any dtype, DN) to its accumulators
    (flat, in place); return the frame's sum per group (whole frame, then each of ``n_bands``
    bands by ``band``). ``pairs`` (3,), unless None, gathers the first two frames' pixels below
    full scale in both: count, sum of their means, sum of squared differences. Whole-array
    numpy: the second frame sets ``s1`` and ``s2`` (the first leaves them as they are), the
    difference from the first frame is taken in float32 where that is exact (integer frames of
    up to 16 bits against a float32 first frame), the full-scale tests only run when the frame
    reaches full scale. :func:`hsiffc.kernels.emva.add_frame` is the same in one compiled
    pass."""
    sums = np.zeros(1 + n_bands)
    sums[0] = frame.sum(dtype=np.float64)
    if n_bands > 0:
        sums[1:] = np.bincount(band, frame, n_bands)
    top = frame.max() >= fs
    if j == 0:
        first[:] = frame
        if top:
            np.greater_equal(frame, fs, out=clip)
        else:
            clip[:] = False
        return sums
    exact32 = first.dtype == np.float32 and frame.dtype.kind in "ui" and frame.itemsize <= 2
    d = np.subtract(frame, first, dtype=np.float32 if exact32 else np.float64)
    if j == 1:
        s1[:] = d
        del d
        np.multiply(s1, s1, out=s2)
        if pairs is not None:
            if top or clip.any():
                ok = first < fs
                if top:
                    ok &= frame < fs
                pairs[0] += ok.sum()
                pairs[1] += 0.5 * (first[ok].sum(dtype=np.float64)
                                   + frame[ok].sum(dtype=np.float64))
                pairs[2] += s2[ok].sum()
            else:  # every pixel below full scale in both: the sums at hand
                pairs[0] += frame.size
                pairs[1] += sums[0] - 0.5 * s1.sum()  # (first + frame) / 2, first = frame - d
                pairs[2] += s2.sum()
    else:
        s1 += d
        s2 += np.multiply(d, d, dtype=np.float64)
    if top:
        clip |= frame >= fs
    return sums


def _finish_step(first, s1, s2, clip, n, band, n_bands, fs, want_mean, want_sum):
    """Reduce a step of ``n`` frames: the sum of the per-pixel temporal variances per group,
    the number of pixels at full scale in some frame, and (else empty) the mean image
    (float32, full scale where clipped) and the sum image (float64). ``s1`` and ``s2`` (only
    read for ``n`` > 1) are used up: the variance is computed in place, no temporaries beside
    the images returned."""
    mean = np.empty(0, np.float32)
    total = np.empty(0)
    if n < 2:
        if want_mean:
            mean = first.astype(np.float32)
            mean[clip] = fs
        if want_sum:
            total = first.astype(np.float64)
        vs = np.zeros(1 + n_bands)
        return vs, float(clip.sum()), mean, total
    inv = 1.0 / n
    if want_mean:
        m = np.multiply(s1, inv)
        m += first
        mean = m.astype(np.float32)
        del m
        mean[clip] = fs
    if want_sum:
        total = np.multiply(first, np.float64(n), dtype=np.float64)
        total += s1
    var = s2  # (s2 - s1^2 / n) / (n - 1), in place
    s1 *= s1
    s1 *= inv
    var -= s1
    if n > 2:
        var /= n - 1
    vs = np.zeros(1 + n_bands)
    vs[0] = var.sum()
    if n_bands > 0:
        vs[1:] = np.bincount(band, var, n_bands)
    return vs, float(clip.sum()), mean, total


def _finish_compiled(first, s1, s2, clip, n, band, n_bands, fs, want_mean, want_sum):
    """:func:`_finish_step` in one compiled pass (:func:`hsiffc.kernels.emva.finish_step`):
    no temporaries beside the images it returns."""
    from ..kernels.emva import finish_step

    mean = np.empty(s1.size if want_mean else 0, np.float32)
    total = np.empty(s1.size if want_sum else 0)
    out = finish_step(first, s1, s2, clip, n, band, n_bands, fs, mean, total)
    return out[:-1], float(out[-1]), mean, total


#: the compiled kernel runs for frames of at least :data:`COMPILED_FRAME_PIXELS` pixels in a
#: set of at least :data:`COMPILED_FROM` pixel-frames. Its first call loads numba's code
#: generator: about 1.2 s of CPU and 130 MB resident here. Per step of two 16-bit frames the
#: numpy form now takes no longer (CPU, two adds and the reduction: 10.4 against 13.6 ms at
#: 1024 x 1024, 47 against 54 ms at 2048 x 2048; benchmarks on random frames, load 5), so the
#: compiled form only runs where numpy's temporaries (a float32 and a float64 difference, 12
#: bytes per pixel: 200 MB at 4096 x 4096) outweigh numba's fixed memory.
#: The choice depends on the frame size, not on the number of steps, so that memory stays flat
#: in the number of steps.
COMPILED_FROM = 1e8
COMPILED_FRAME_PIXELS = 1 << 24


def _first_dtype(dtype) -> type:
    """float32 for the first frame of a step where it holds the frame's values exactly (integers
    of up to 16 bits, float32), else float64."""
    dtype = np.dtype(dtype)
    exact = (dtype.kind in "ui" and dtype.itemsize <= 2) or dtype == np.float32
    return np.float32 if exact else np.float64


class _StepState:
    """Accumulators of the step being read (buffers reused from step to step)."""

    def __init__(self, n_pixels):
        self.first = None  # allocated for the first frame's dtype
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


def reduce_frames(source, *, mosaic_bands: bool = True, keep_step_means=False,
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
    keep_step_means : bool or array of int
        Keep every step's per-pixel mean image and the pair statistics (for the leakage
        calibration); given pixels (flat indices), their means only.
    spatial_steps : sequence of int, optional
        The steps of the spatial stack (default: ``meta["spatial_steps"]``, else the steps with
        more than twice the median number of frames).

    Returns
    -------
    dict
        ``steps`` (per-step arrays ``step``, ``kind``, ``exposure_ms``, ``photons``,
        ``n_frames``, ``spatial``, ``clipped_share``), ``groups`` (per group: ``label``,
        ``band``, ``n_pixels``, ``mean_dn`` and ``var_dn2`` per step), ``images`` (the spatial
        stacks' ``sum`` images, mean temporal variances per group ``var_mean`` and frame
        counts, by kind, or None),
        ``frame_shape``, ``n_pixels``, ``bit_depth``, ``full_scale_dn``; with
        ``keep_step_means`` also ``step_means`` (S, H, W) float32, or (S, 1, N) at N given
        pixels (``step_mean_pixels``, else None), and ``pairs`` (S, 3) (over all pixels).

    Raises
    ------
    DataFormatError
        A step whose frames are not contiguous in the stream.
    """
    meta = getattr(source, "meta", {}) or {}
    frame_shape = tuple(source.frame_shape)
    pixels = None
    if keep_step_means is not None and not isinstance(keep_step_means, bool):
        pixels = np.asarray(keep_step_means, np.int64).ravel()
    keep_step_means = pixels is not None or bool(keep_step_means)
    mean_shape = frame_shape if pixels is None else (1, pixels.size)
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
    use_compiled = (n_total >= COMPILED_FRAME_PIXELS
                    and float(source.n_frames) * n_total >= COMPILED_FROM)
    if use_compiled:
        from ..kernels import emva as compiled

        add_frame, reduce_step = compiled.add_frame, _finish_compiled
    else:
        add_frame, reduce_step = _add_frame, _finish_step
    st = _StepState(n_total)
    rows: list[dict] = []
    images: dict = {}
    means: list = []
    done: set = set()

    def finish():
        if st.step is None:
            return
        is_sp = st.step in spatial
        vs, n_clip, mean_img, sum_img = reduce_step(
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
                                                "var_mean": vs / n_pix,
                                                "L": st.n, "step": st.step})
        elif keep_step_means:
            means.append((st.step, (mean_img if pixels is None else mean_img[pixels])
                           .reshape(mean_shape)))
        done.add(st.step)

    for frame, step, kind, exposure, photons in _frames_of(source):
        if step != st.step:
            finish()
            if step in done:
                raise DataFormatError(f"the frames of step {step} are not one after the other; "
                                      "EMVA 1288 lists each step's images together: fix the "
                                      "descriptor's order", path=where)
            st.reset(step, (kind, exposure, photons))
        if st.first is None:
            st.first = np.empty(n_total, _first_dtype(frame.dtype))
        sums = add_frame(np.ascontiguousarray(frame).reshape(-1), st.n, st.first, st.s1,
                         st.s2, st.clip, band, n_bands, fs,
                         st.pairs if keep_step_means or use_compiled else None)
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
                             np.empty((0,) + mean_shape, np.float32))
        out["step_mean_pixels"] = pixels
        out["sweep_step_info"] = {k: np.array([r[k] for r in sweep_rows]) for k in
                                  ("step", "kind", "exposure_ms", "photons", "n_frames")}
        out["pairs"] = np.array([r["pairs"] for r in sweep_rows])
    return out
