"""EMVA 1288 step statistics reduced while the frames are read: memory bounded by a few frames.

Every frame goes once through a compiled kernel (numba, without the GIL) that adds it to
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
threads while the kernel works on the current one: both cores are busy. The kernels run on
one thread: a frame takes well under a millisecond per 100 000 pixels, less than its decoding,
and numba's parallel launch costs more than it saves on frames up to a few megapixels when the
cores are shared (measured 4.0 ms against 0.35 ms per 128 x 256 frame here).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from ..errors import DataFormatError

__all__ = ["reduce_frames", "SPATIAL_FACTOR"]

SPATIAL_FACTOR = 2.0  # a step with more than this x the median frames per step is a spatial stack


@njit(cache=True, nogil=True)
def _add_frame(frame, j, first, s1, s2, clip, band, fs, gpart, ppart):
    """Add frame number ``j`` of a step to its accumulators (in place). ``band`` (H, W) int
    holds each pixel's group index after the whole frame's (-1: none); ``gpart`` (H, G) row
    sums per group; ``ppart`` (H, 3) the pair statistics of the first two frames."""
    h, w = frame.shape
    for r in range(h):
        for c in range(w):
            v = np.float64(frame[r, c])
            gpart[r, 0] += v
            g = band[r, c]
            if g >= 0:
                gpart[r, g + 1] += v
            at_fs = v >= fs
            if j == 0:
                first[r, c] = v
                s1[r, c] = 0.0
                s2[r, c] = 0.0
                clip[r, c] = at_fs
            else:
                a = first[r, c]
                d = v - a
                s1[r, c] += d
                s2[r, c] += d * d
                clip[r, c] |= at_fs
                if j == 1 and a < fs and v < fs:
                    ppart[r, 0] += 1.0
                    ppart[r, 1] += 0.5 * (a + v)
                    ppart[r, 2] += d * d


@njit(cache=True, nogil=True)
def _finish_step(first, s1, s2, clip, n, band, n_groups, fs, mean_out, var_out, sum_out,
                 want_mean, want_images):
    """Reduce a step of ``n`` frames: per-row sums of the per-pixel temporal variance per group
    (H, G), the number of clipped pixels per row; optionally the mean image (float32, full
    scale where clipped) and the sum and variance images (float64)."""
    h, w = first.shape
    vpart = np.zeros((h, n_groups))
    cpart = np.zeros(h)
    inv = 1.0 / n
    for r in range(h):
        for c in range(w):
            a = s1[r, c]
            if n > 1:
                var = (s2[r, c] - a * a * inv) / (n - 1)
            else:
                var = 0.0
            vpart[r, 0] += var
            g = band[r, c]
            if g >= 0:
                vpart[r, g + 1] += var
            if clip[r, c]:
                cpart[r] += 1.0
            if want_mean:
                mean_out[r, c] = fs if clip[r, c] else first[r, c] + a * inv
            if want_images:
                sum_out[r, c] = first[r, c] * n + a
                var_out[r, c] = var
    return vpart, cpart


class _StepState:
    """Accumulators of the step being read (buffers reused from step to step)."""

    def __init__(self, shape, n_groups):
        self.first = np.empty(shape)
        self.s1 = np.empty(shape)
        self.s2 = np.empty(shape)
        self.clip = np.empty(shape, np.bool_)
        self.n_groups = n_groups
        self.reset(None, None)

    def reset(self, step, meta):
        self.step, self.meta, self.n = step, meta, 0
        self.frame_sums: list = []
        self.ppart = np.zeros((self.first.shape[0], 3))


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
    mosaic = getattr(source, "mosaic", None)
    if mosaic_bands and mosaic is not None:
        return mosaic.band_map(frame_shape).astype(np.int64), mosaic.n_bands
    return np.full(frame_shape, -1, np.int64), 0


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
    counts = np.bincount(band.ravel() + 1, minlength=n_groups + 1)
    n_pix = np.concatenate([[band.size], counts[1:n_groups]]).astype(np.float64)
    if spatial_steps is None:
        spatial_steps = meta.get("spatial_steps")
    if spatial_steps is None:
        steps_all = np.asarray(source.step)
        ids, cnt = np.unique(steps_all, return_counts=True)
        spatial_steps = ids[cnt > SPATIAL_FACTOR * np.median(cnt)].tolist()
    spatial = {int(s) for s in spatial_steps}
    st = _StepState(frame_shape, n_groups)
    rows: list[dict] = []
    images: dict = {}
    means: list = []
    done: set = set()
    h = frame_shape[0]

    def finish():
        if st.step is None:
            return
        is_sp = st.step in spatial
        sum_img = np.empty(frame_shape) if is_sp else np.empty((1, 1))
        var_img = np.empty(frame_shape) if is_sp else np.empty((1, 1))
        mean_img = (np.empty(frame_shape, np.float32) if keep_step_means and not is_sp
                    else np.empty((1, 1), np.float32))
        vpart, cpart = _finish_step(st.first, st.s1, st.s2, st.clip, st.n, band, n_groups, fs,
                                    mean_img, var_img, sum_img, keep_step_means and not is_sp,
                                    is_sp)
        fm = np.array(st.frame_sums) / n_pix  # (L, G) frame means per group
        mean = fm.mean(axis=0)
        if st.n > 1:
            var = vpart.sum(axis=0) / n_pix - fm.var(axis=0, ddof=1)
        else:
            var = np.full(n_groups, np.nan)
        kind, exposure, photons = st.meta
        rows.append({"step": st.step, "kind": kind, "exposure_ms": exposure,
                     "photons": photons, "n_frames": st.n, "spatial": is_sp,
                     "clipped_share": float(cpart.sum()) / band.size, "mean": mean,
                     "var": var, "pairs": st.ppart.sum(axis=0)})
        if is_sp:
            images.setdefault(kind, []).append({"sum": sum_img, "var": var_img, "L": st.n,
                                                "step": st.step})
        elif keep_step_means:
            means.append((st.step, mean_img))
        done.add(st.step)

    for frame, step, kind, exposure, photons in _frames_of(source):
        if step != st.step:
            finish()
            if step in done:
                raise DataFormatError(f"the frames of step {step} are not one after the other; "
                                      "EMVA 1288 lists each step's images together: fix the "
                                      "descriptor's order", path=where)
            st.reset(step, (kind, exposure, photons))
        gpart = np.zeros((h, n_groups))
        _add_frame(frame, st.n, st.first, st.s1, st.s2, st.clip, band, fs, gpart, st.ppart)
        st.frame_sums.append(gpart.sum(axis=0))
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
    labels = ["all pixels"] + [f"band {b}" for b in range(n_bands)]
    groups = [{"label": labels[g], "band": None if g == 0 else g - 1,
               "n_pixels": int(n_pix[g]),
               "mean_dn": np.array([r["mean"][g] for r in rows]),
               "var_dn2": np.array([np.nan if r["spatial"] else r["var"][g] for r in rows])}
              for g in range(n_groups)]
    out = {"steps": info, "groups": groups, "frame_shape": list(frame_shape),
           "n_pixels": int(band.size), "bit_depth": bit_depth, "full_scale_dn": int(fs),
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
