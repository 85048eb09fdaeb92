"""The GPU path against the CPU path on the same frames (used by tests/gpu/test_gpu.py in numba's
CUDA simulator and by benchmarks/gpu.py on a device).

:func:`scene` makes a simulated sensor, its calibration and a test frame; :func:`compare`
runs one pipeline both ways and returns the largest differences.
"""

from __future__ import annotations

import numpy as np

from ..calibrate import calibrate
from ..data.dq import DQ_DTYPE
from ..data.frame import Frame
from ..simulate import PAPER_LIGHT_W_M2, MosaicSensor
from ..stages import Pipeline, create
from ..stages.defaults import default_pipeline

__all__ = ["compare", "compare_matrix", "holed", "hollow", "matrix_pipeline", "more_pipelines", "pipelines",
           "scene"]


def scene(shape, *, seed: int = 0, n_exposures: int = 12):
    """(sensor, calibration, raw test frame at 16.125 ms) of a simulated mosaic sensor."""
    sensor = MosaicSensor(tuple(shape), seed=seed)
    sweep = sensor.sweep(np.round(np.geomspace(2, 400, n_exposures), 3), "lamp A",
                         irradiance_w_m2=0.25 * PAPER_LIGHT_W_M2["training"], n_frames=1,
                         seed=seed + 1)
    cal = calibrate(sweep)
    raw = sensor.capture(16.125, "lamp B", irradiance_w_m2=PAPER_LIGHT_W_M2["test"],
                         seed=seed + 3).frames[0]
    return sensor, cal, raw


def pipelines(cal) -> dict:
    """The fitted pipelines the GPU runs: the default correction, it with a bilinear cube,
    and dark + mask alone with a cube."""
    base = default_pipeline(cal)
    cube = create("reconstruct", method="bilinear").fit([])
    front = Pipeline(base.steps[:2])
    return {"correct": base, "correct+bilinear": Pipeline(base.steps + [("cube", cube)]),
            "mask+bilinear": Pipeline(front.steps + [("cube", cube)])}


def more_pipelines(sensor, cal, *, seed: int = 0) -> dict:
    """The other pipelines the GPU runs: dark + mask + two-point FFC (fitted on flats of
    ``sensor`` at two exposures, each band's chosen by alpha), it with a nearest cube, and
    PPID cubes after the mask alone and after the default correction."""
    from ..data.frame import Frame as _Frame

    base = default_pipeline(cal)
    front = Pipeline(base.steps[:2])
    flats = _Frame.list_from_sweep(sensor.sweep([8.0, 16.0], "lamp A",
                                                irradiance_w_m2=PAPER_LIGHT_W_M2["training"],
                                                n_frames=2, seed=seed + 7))
    two = Pipeline(front.steps + [("ffc", create("two_point_ffc", calibration=cal))]).fit(flats)
    cube = (lambda m: ("cube", create("reconstruct", method=m).fit([])))  # noqa: E731
    return {"two_point": two, "two_point+nearest": Pipeline(two.steps + [cube("nearest")]),
            "mask+ppid": Pipeline(front.steps + [cube("ppid")]),
            "correct+ppid": Pipeline(base.steps + [cube("ppid")])}


def _ulps(a, b, scale):
    """Largest |a - b| in float32 ulps of ``scale`` (ulp at the magnitude ``scale``)."""
    diff = np.abs(a.astype(np.float64) - b.astype(np.float64))
    return float(diff.max() / np.spacing(np.float32(max(scale, 1e-30)))) if diff.size else 0.0


def compare(pipe, gpu, frame: Frame) -> dict:
    """Largest differences between the CPU and GPU frames of ``frame``: ``data_ulps_of_value``
    (per value), ``data_ulps_of_max`` (against the frame's largest value), the count of DQ
    values that differ and of alpha values that differ beyond 1 ulp."""
    cpu = pipe.transform(frame)
    dev = gpu.transform(frame)
    c, g = cpu.data, dev.data
    rel = np.abs(c.astype(np.float64) - g) / np.maximum(np.spacing(np.abs(c)), 1e-45)
    out = {"shape": list(c.shape),
           "data_ulps_of_value": float(rel.max()),
           "data_ulps_of_max": _ulps(c, g, float(np.abs(c).max())),
           "dq_differ": int(np.count_nonzero(cpu.dq.astype(DQ_DTYPE) != dev.dq)),
           "history_equal": cpu.history == dev.history,
           "meta_equal": {k: v for k, v in cpu.meta.items() if k != "history"}
           == {k: v for k, v in dev.meta.items() if k != "history"}}
    if cpu.alpha is not None and dev.alpha is not None:
        ca, ga = np.asarray(cpu.alpha, np.float64), np.asarray(dev.alpha, np.float64)
        same = (ca == ga) | (np.abs(ca - ga) <= np.spacing(np.abs(ca).astype(np.float32)))
        out["alpha_differ"] = int(np.count_nonzero(~same))
    return out


def holed(frame: Frame, *, seed: int = 0) -> Frame:
    """``frame`` with flagged samples the reconstruction must bridge: a block of DEAD pixels
    two tiles high and wide (values with no usable sample in S1, some in neither S1 nor S2:
    the band-median fill) and 2 % scattered HOT pixels."""
    rng = np.random.default_rng(seed)
    dq = frame.dq.copy()
    H, W = dq.shape
    dq[H // 3:H // 3 + 6, W // 3:W // 3 + 10] |= DQ_DTYPE(8)  # DEAD
    dq[rng.random(dq.shape) < 0.02] |= DQ_DTYPE(16)  # HOT
    return frame.replace(dq=dq)


def hollow(frame: Frame) -> Frame:
    """``frame`` with a DEAD block of 7 rows x 13 columns around its centre: for a 2 x 4
    mosaic the PPI is undefined at the centre (its window and every neighbour one tile away
    are flagged), where PPID takes the twice-wide tent's plain value; values around it have
    no usable sample within twice the tile (the band-median fill)."""
    dq = frame.dq.copy()
    H, W = dq.shape
    y, x = H // 2, W // 2 - 1
    dq[max(y - 3, 0):y + 4, max(x - 6, 0):x + 7] |= DQ_DTYPE(8)  # DEAD
    return frame.replace(dq=dq)


def matrix_pipeline(pipe, n_virtual: int = 5, *, seed: int = 0):
    """``pipe`` (dark + mask [+ model FFC], no cube) with a bilinear cube and a random
    spectral correction matrix (a zero coefficient, and a row of one band), as a fitted
    ``reconstruct`` stage with ``correction="imec"`` would hold it."""
    n_bands = pipe.steps[0][1].calibration_product().mosaic.n_bands
    rng = np.random.default_rng(seed)
    m = rng.normal(0.0, 0.5, (n_virtual, n_bands))
    m[:, 0] += 1.0
    m[min(2, n_virtual - 1), min(3, n_bands - 1)] = 0.0
    m[-1, :] = 0.0
    m[-1, n_bands - 2] = 2.0
    rec = create("reconstruct", method="bilinear", correction="imec", imec_xml="matrix.xml")
    rec.matrix_ = m
    rec.virtual_wavelengths_nm_ = [500.0 + 10.0 * i for i in range(n_virtual)]
    rec.fitted_ = True
    return Pipeline(list(pipe.steps) + [("cube", rec)])


def compare_matrix(pipe, gpu, frame: Frame) -> dict:
    """:func:`compare` for a pipeline ending in a correction matrix: the value's error in
    units of float32 epsilon times the sum of the absolute terms (a sum with cancellation is
    only as exact as its terms), DQ, alpha, history and metadata."""
    cpu = pipe.transform(frame)
    dev = gpu.transform(frame)
    bands = Pipeline(pipe.steps[:-1] + [("cube", create("reconstruct", method="bilinear")
                                         .fit([]))]).transform(frame).data
    m = np.abs(np.asarray(pipe.steps[-1][1].matrix_, np.float64))
    terms = np.einsum("hwb,vb->hwv", np.abs(bands.astype(np.float64)), m)
    err = np.abs(cpu.data.astype(np.float64) - dev.data)
    return {"shape": list(cpu.data.shape),
            "err_in_eps_of_terms": float((err / (terms * np.finfo(np.float32).eps
                                                  + 1e-30)).max()),
            "dq_differ": int(np.count_nonzero(cpu.dq != dev.dq)),
            "alpha_differ": int(np.count_nonzero(np.asarray(cpu.alpha) != dev.alpha)),
            "history_equal": cpu.history == dev.history,
            "meta_equal": {k: v for k, v in cpu.meta.items() if k != "history"}
            == {k: v for k, v in dev.meta.items() if k != "history"}}
