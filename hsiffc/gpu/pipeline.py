"""A fitted pipeline on the GPU: :class:`GpuPipeline` (``Pipeline.to("cuda")``).

Runs on the device: ``dark`` + ``alpha_mask`` (paper alpha) [+ ``model_ffc`` or
``two_point_ffc``] [+ ``reconstruct`` with ``method`` "nearest", "bilinear" or "ppid",
``resolution="full"``, with or without a spectral correction matrix (``correction="imec"``
or ``"derived"``)].
Other stages are refused at construction with one line naming the step. Calibration planes go
to the device once; the dark of each exposure once (the dark stage's own
:meth:`~hsiffc.stages.dark.DarkSubtract.dark_for`, so it is the CPU's plane).

Frames the kernels do not take are corrected by the CPU pipeline instead, the same frame:
an exposure of 0 ms (the model FFC's special case). Values of a cube whose twice-wide
support holds no usable sample take the exact band median (the CPU's fill): found on the
device only for the frames that have such values (PPID's band levels need the medians of
every frame), or on the host for more than :data:`~hsiffc.gpu.kernels.MAX_BANDS` bands.
"""

from __future__ import annotations

from collections import OrderedDict
from typing import NamedTuple

import numpy as np

from ..data.dq import DQ, DQ_DTYPE
from ..errors import ParameterError
from ..data.frame import Frame
from ..kernels.lattice import lattice_arrays
from ..kernels.operands import float_array
from ..reconstruct.prepare import band_medians, periodic_index, ppi_kernel, prepare
from . import cuda_module
from .pack import DATA_DTYPES, check_dtypes, pack_cpu

__all__ = ["GpuPipeline", "StreamItem"]

_BLOCK = (32, 8)  # threads per block (x along the row); GpuPipeline.block may change it
_TOL_DN = 1e-9  # hsiffc.flatfield.model_based's tolerance of the inversion
_MAX_ITER = 60  # hsiffc.leakage.model.invert_response's


class StreamItem:
    """One corrected frame or cube from :meth:`GpuPipeline.stream` (or
    :meth:`hsiffc.stages.Pipeline.stream`): ``data``, ``dq``, ``alpha`` (None unless asked
    for) in the stream's output types, and ``meta`` (the frame's metadata with the history of
    every step)."""

    __slots__ = ("alpha", "data", "dq", "meta")

    def __init__(self, data, dq, alpha, meta):
        self.data, self.dq, self.alpha, self.meta = data, dq, alpha, meta

    def to_frame(self) -> Frame:
        """As a :class:`~hsiffc.data.frame.Frame` (float32 data, uint32 DQ)."""
        return Frame(self.data.astype(np.float32), self.dq.astype(DQ_DTYPE), self.meta,
                     alpha=self.alpha)


class DeviceFrame(NamedTuple):
    """One frame on the device, as :meth:`GpuPipeline._launch` takes it."""

    d_raw: object  # the frame as read, on the device
    d_dq: object  # its DQ on the device (read where has_dq)
    has_dq: bool
    shape: tuple  # (H, W)
    exposure_ms: float
    bit_depth: int
    mosaic: object  # Mosaic or None


class OutputTypes(NamedTuple):
    """What :meth:`GpuPipeline._launch` writes: the data type's index in
    :data:`~hsiffc.gpu.pack.DATA_DTYPES` (``mode``), a uint8 DQ (``fold``), the alpha."""

    mode: int
    fold: bool
    with_alpha: bool


class _Pending(NamedTuple):
    """A frame of :meth:`GpuPipeline.stream` whose result is not handed out yet: run on the
    device (``where`` "gpu", ``slot`` its buffers) or by the CPU pipeline ("cpu", ``slot``
    the output types)."""

    where: str
    item: object
    raw: object
    exposure_ms: float
    bit_depth: int
    mosaic: object
    meta: dict
    slot: object


def _entry(name, stage):
    return {"step": name, "stage": stage.name or type(stage).__name__,
            "params": stage.json_params(), "status": "ok"}


def plan(pipeline):
    """``(dark, mask, ffc or None, reconstruct or None)`` of a pipeline the GPU runs, with
    their step names; ParameterError naming the first step it cannot run. A step runs on the
    GPU as what its stage declares it computes (:attr:`hsiffc.stages.base.Stage.gpu_as`)."""
    steps = list(pipeline.steps)
    kinds = [(("dark",), "dark"), (("alpha_mask",), "alpha_mask"),
             (("model_ffc", "two_point_ffc"), "ffc"), (("reconstruct",), "reconstruct")]
    found = {}
    i = 0
    for roles, key in kinds:
        if i < len(steps) and getattr(steps[i][1], "gpu_as", None) in roles:
            found[key] = steps[i]
            i += 1
        elif key in ("dark", "alpha_mask"):
            name = steps[i][0] if i < len(steps) else "(none)"
            raise ParameterError(f"device='cuda' runs dark, alpha_mask[, model_ffc or "
                                 f"two_point_ffc][, reconstruct]; step {name!r} is not {key}: "
                                 "run this pipeline with device='cpu'")
    if i < len(steps):
        name, stage = steps[i]
        raise ParameterError(f"step {name!r} ({stage.name}) does not run on the GPU (it runs "
                             "dark, alpha_mask, model_ffc or two_point_ffc, and reconstruct "
                             "at full resolution); run this pipeline with device='cpu'")
    mask = found["alpha_mask"][1]
    if mask.method != "paper":
        raise ParameterError(f"step {found['alpha_mask'][0]!r}: the GPU computes the paper "
                             f"alpha, not method={mask.method!r}; use device='cpu'")
    rec = found.get("reconstruct")
    if rec is not None:
        r = rec[1]
        if r.method not in GPU_METHODS or r.resolution != "full":
            raise ParameterError(f"step {rec[0]!r}: the GPU reconstructs method "
                                 f"{', '.join(GPU_METHODS)} at resolution='full' (with or "
                                 f"without a correction matrix); got method={r.method!r}, "
                                 f"resolution={r.resolution!r}: use device='cpu'")
    for _, stage in steps:
        stage.check_is_fitted()
    return found["dark"], found["alpha_mask"], found.get("ffc"), rec


#: the reconstruction methods the GPU runs (at full resolution)
GPU_METHODS = ("nearest", "bilinear", "ppid")


def _phase_band(lattices, period) -> np.ndarray:
    """Band of each tile phase ``(y mod ph) * pw + x mod pw`` (-1: none)."""
    ph, pw = (int(v) for v in period)
    table = np.full(ph * pw, -1, np.int64)
    for b, lat in enumerate(lattices):
        for r, c in lat:
            table[r * pw + c] = b
    return table


def _pinned_zeros(cuda, n, dtype):
    """Zeros in pinned host memory: the per-frame reset of a counter is an asynchronous copy
    on the frame's stream."""
    a = cuda.pinned_array(n, dtype)
    a[:] = 0
    return a


class GpuPipeline:
    """A fitted :class:`~hsiffc.stages.Pipeline` run on an NVIDIA GPU (see the module).

    ``transform(frame)`` gives the CPU pipeline's frame (within the tolerance of
    :mod:`hsiffc.gpu.kernels`); ``stream(frames)`` yields corrected frames or cubes with
    upload, compute and download overlapped; ``to("cpu")`` gives the CPU pipeline back.
    """

    #: threads per block of the frame kernels (x along the row); the tests make it small so
    #: that numba's simulator, one Python thread per CUDA thread, stays fast
    block = _BLOCK

    def __init__(self, pipeline):
        self.pipeline = pipeline
        self.dark, self.mask, self.ffc, self.rec = plan(pipeline)
        self.cuda = cuda_module()
        from . import kernels
        self.k = kernels
        self._planes = {}  # per frame shape: the device planes
        self._darks = OrderedDict()  # (shape, exposure) -> device dark
        self._rec_meta_cache = {}  # mosaic (by value) -> what reconstruct adds to the metadata
        self._transform_slots = [None, None]  # transform's device buffers, kept: a batch calls
        # it once per frame

    def __repr__(self):
        return f"GpuPipeline({self.pipeline!r})"

    @property
    def steps(self):
        return self.pipeline.steps

    def to(self, device: str):
        """``"cpu"``: the CPU pipeline; ``"cuda"``: this one."""
        return self.pipeline if device == "cpu" else self

    # -- device constants ----------------------------------------------------------------------
    def _const(self, frame_like_shape, exposure_ms, bit_depth, mosaic):
        shape = tuple(frame_like_shape)
        planes = self._planes.get(shape)
        if planes is None:
            planes = self._upload(shape, bit_depth, mosaic)
            self._planes[shape] = planes
        key = (shape, float(exposure_ms))
        dark = self._darks.get(key)
        if dark is None:
            plane, how = self.dark[1].dark_for(exposure_ms, shape)
            dark = (self.cuda.to_device(np.ascontiguousarray(plane, np.float32)), how,
                    np.asarray(plane, np.float32))
            self._darks[key] = dark
            while len(self._darks) > 4:
                self._darks.popitem(last=False)
        return planes, dark

    def _upload(self, shape, bit_depth, mosaic):
        cuda = self.cuda
        probe = Frame(np.zeros(shape, np.float32), np.zeros(shape, DQ_DTYPE),
                      {"exposure_ms": 1.0, "bit_depth": int(bit_depth), "mosaic": mosaic})
        cal = self.mask[1].calibration_for(probe)
        dev = lambda a: cuda.to_device(np.ascontiguousarray(a))  # noqa: E731
        pix = np.zeros(shape, DQ_DTYPE)
        if cal.arrays.get("flags") is not None:
            pix |= np.asarray(cal.arrays["flags"], DQ_DTYPE)
        prep = cal.prepare()  # the float32 planes the CPU's fused pass reads
        p = {"cal": cal, "a32": dev(prep.a), "b32": dev(prep.b)}
        one = dev(np.zeros((1, 1), np.float32))
        p["two_point"] = None
        if self.ffc is not None and self.ffc[1].gpu_as == "two_point_ffc":
            ffc = self.ffc[1]
            if ffc.gain_.shape != tuple(shape):
                raise ValueError(f"frame shape {tuple(shape)} differs from the flat's "
                                 f"{ffc.gain_.shape}")
            pix |= np.asarray(ffc.dq_, DQ_DTYPE)
            band_map = probe.band_map()
            paper = ffc.normalisation == "paper"
            flat_mean = ffc.band_flat_mean(band_map) if paper else np.ones(1)
            n = len(flat_mean) if paper else int(band_map.max()) + 1
            if paper and n > self.k.MAX_BANDS:
                raise ValueError(f"the two-point FFC on the GPU takes up to "
                                 f"{self.k.MAX_BANDS} bands; this one has {n}: use "
                                 "device='cpu'")
            p["two_point"] = {"paper": paper, "n": n,
                              "gain": dev(np.asarray(ffc.gain_, np.float32)),
                              "band": dev(np.asarray(band_map, np.int32)),
                              "flat_mean": dev(np.asarray(flat_mean, np.float64)),
                              "ones": dev(np.ones(n, np.float32))}
            p.update(a=one, b=one, base=one, log_ratio=one, has_sweep=False)
        elif self.ffc is not None:
            ffc = self.ffc[1]
            cal_f = ffc._cal_for(probe)
            pix |= np.asarray(ffc.dq_, DQ_DTYPE)
            has_sweep = ffc.gain_sweep_ is not None
            prep_f = ffc.prepare()
            p.update(a=dev(float_array(cal_f.a)), b=dev(float_array(cal_f.b)),
                     base=dev(float_array(ffc.gain_sweep_ if has_sweep else ffc.gain_)),
                     log_ratio=(dev(float_array(prep_f.log_ratio)) if has_sweep
                                else one),
                     has_sweep=has_sweep,
                     # the UNCERTAIN test c > e signal^2 (float32 planes), as on the CPU
                     uncertain=(None if prep_f.uncertain is None else
                                tuple(dev(np.asarray(x, np.float32))
                                      for x in prep_f.uncertain)))
        else:
            p.update(a=one, b=one, base=one, log_ratio=one, has_sweep=False)
        p["pix"] = dev(pix)
        if self.rec is not None:
            if mosaic is None:
                raise ValueError("reconstruct needs the frame's mosaic layout (meta['mosaic']); "
                                 "this frame has none")
            lat = prepare(np.zeros(shape, np.float32), mosaic, None).lattices()
            lat_r, lat_c, lat_start = lattice_arrays(lat)
            ph, pw = (int(v) for v in mosaic.tile_shape)
            H, W = shape
            p.update(lat_r=dev(lat_r), lat_c=dev(lat_c), lat_start=dev(lat_start),
                     period=(ph, pw), n_bands=len(lat),
                     # the cube kernel's phases and weights (no division on the device)
                     ymod=dev(np.arange(H, dtype=np.int64) % ph),
                     xmod=dev(np.arange(W, dtype=np.int64) % pw),
                     wy_of=dev(np.arange(ph, dtype=np.float64) / ph),
                     wx_of=dev(np.arange(pw, dtype=np.float64) / pw),
                     no_medians=dev(np.zeros(1, np.float32)),
                     always=dev(np.ones(1, np.int64)),
                     phase_band=dev(_phase_band(lat, mosaic.tile_shape)))
            method = self.rec[1].method
            pos = [np.argwhere(np.asarray(mosaic.pattern) == b) for b in range(len(lat))]
            p.update(method=method, offset=(int(mosaic.offset[0]) % ph,
                                            int(mosaic.offset[1]) % pw),
                     pat_r=dev(np.array([r for q in pos for r, _ in q] or [0], np.int64)),
                     pat_c=dev(np.array([c for q in pos for _, c in q] or [0], np.int64)),
                     pat_start=dev(np.cumsum([0] + [len(q) for q in pos]).astype(np.int64)))
            if method == "ppid":
                if len(lat) > self.k.MAX_BANDS:
                    raise ValueError(f"PPID on the GPU takes up to {self.k.MAX_BANDS} bands "
                                     f"(its band levels are found on the device); this mosaic "
                                     f"has {len(lat)}: use device='cpu'")
                kx, ky = ppi_kernel(pw), ppi_kernel(ph)
                p.update(band_of=dev(np.ascontiguousarray(mosaic.band_map((ph, pw)),
                                                          np.int64)),
                         rows=dev(periodic_index(H, ph, ky.size // 2).astype(np.int64)),
                         cols=dev(periodic_index(W, pw, kx.size // 2).astype(np.int64)),
                         kx=dev(np.asarray(kx, np.float64)), ky=dev(np.asarray(ky, np.float64)),
                         win=((2 * ph - 1 + ky.size - 1) // 2, (2 * pw - 1 + kx.size - 1) // 2))
            rec = self.rec[1]
            if rec.correction is not None:  # the matrix as the CPU's float32 product
                m = np.asarray(rec.matrix_, np.float64)  # takes it (transposed)
                if m.shape[1] != len(lat):
                    raise ValueError(f"the correction matrix has {m.shape[1]} band columns "
                                     f"but the frame's mosaic has {len(lat)} bands")
                p.update(coef=dev(np.ascontiguousarray(m.T, np.float32)),
                         support=dev(np.ascontiguousarray((m != 0).T, np.uint8)),
                         n_virtual=m.shape[0])
        return p

    # -- one frame ----------------------------------------------------------------------------
    def _launch(self, frame: DeviceFrame, bufs, types: OutputTypes, stream, eager_fill=False):
        """Queue the kernels of one frame on ``stream``. A cube's values with no usable
        sample within twice the tile are left NaN and listed, and filled by
        :meth:`_fill_device` once the frame's count is back on the host (no launch on the
        frames that have none); ``eager_fill`` queues the fill's passes at once instead,
        each doing nothing unless a value was listed (the device-only benchmark)."""
        d_raw, d_dq, has_dq, shape, exposure_ms, bit_depth, mosaic = frame
        mode, fold, with_alpha = types
        planes, (d_dark, _, _) = self._const(shape, exposure_ms, bit_depth, mosaic)
        cal = planes["cal"]
        mask = self.mask[1]
        H, W = shape
        bx, by = self.block
        grid = ((W + bx - 1) // bx, (H + by - 1) // by)
        ffc = self.ffc[1] if self.ffc is not None else None
        const = 0 if cal.in_domain(exposure_ms) else int(DQ.OUT_OF_DOMAIN)
        do_model = ffc is not None and planes["two_point"] is None
        k = self.k
        k.correct[grid, self.block, stream](
            k.RawFrame(d_raw, d_dq, has_dq, float(2 ** int(bit_depth) - 1), float(exposure_ms),
                       d_dark),
            k.MaskTerms(planes["a32"], planes["b32"], planes["pix"], const,
                        float(mask.threshold_percent), float(cal.domain["full_scale_dn"])),
            k.ModelTerms(do_model, planes["a"], planes["b"], planes["base"],
                         planes["log_ratio"], planes["has_sweep"], 0.0,
                         float(2 ** int(bit_depth) - 1),
                         float(ffc.flat_alpha_percent) if do_model else 0.0,
                         float(ffc.alpha_limit_percent) if do_model else 0.0, 1.0, _TOL_DN,
                         _MAX_ITER),
            k.FrameOut(bufs["frame"], bufs["alpha"], bufs["fdq"]))
        if do_model and planes.get("uncertain") is not None:
            self.k.flag_uncertain[grid, self.block, stream](
                bufs["frame"], bufs["fdq"], *planes["uncertain"], np.uint32(DQ.UNCERTAIN))
        if planes["two_point"] is not None:
            self._two_point(planes["two_point"], d_raw, bufs, grid, stream)
        if self.rec is None:
            self.k.pack2d[grid, self.block, stream](bufs["frame"], bufs["fdq"], mode, fold,
                                                bufs["out"], bufs["out_dq"])
            return
        bufs["missing"].copy_to_device(bufs["zeros"], stream=stream)
        ppid = planes["method"] == "ppid"
        medians = self._medians(planes, bufs, stream, always=ppid) if ppid else None
        if ppid:
            self._ppi(planes, bufs, medians, with_alpha, grid, stream)
        cube = bufs if "coef" not in planes else {
            **bufs, "out": bufs["cube"], "out_dq": bufs["cube_dq"],
            "out_alpha": bufs["cube_alpha"]}
        m, f = (mode, fold) if "coef" not in planes else (0, False)
        self._bilinear(planes, cube, m, f, with_alpha, medians, stream)
        if medians is None and eager_fill:
            self._fill_missing(planes, bufs, cube, m, stream)
        if "coef" in planes:
            self._matrix(planes, bufs, mode, fold, with_alpha, stream)

    def _fill_missing(self, planes, bufs, cube, mode, stream):
        """The listed values of ``cube`` (its ``out`` and ``out_dq``) filled with the exact
        band medians, found on the device (passes that do nothing if none was listed)."""
        medians = self._medians(planes, bufs, stream)
        if medians is not None:
            self.k.fill_missing[32, 128, stream](bufs["missing"], bufs["miss_list"], medians,
                                                 mode, cube["out"], cube["out_dq"])

    def _fill_device(self, slot):
        """A frame whose cube listed values to fill (the count is on the host): the band
        medians and the fill on the device, the correction matrix again if there is one, the
        output downloaded again (synchronous: such frames are rare)."""
        dev, st, planes = slot["dev"], slot["stream"], slot["planes"]
        if "coef" in planes:
            cube = {**dev, "out": dev["cube"], "out_dq": dev["cube_dq"]}
            self._fill_missing(planes, dev, cube, 0, st)
            self._matrix(planes, dev, slot["mode"], slot["fold"], slot["alpha"], st)
        else:
            self._fill_missing(planes, dev, dev, slot["mode"], st)
        self._download(slot)
        st.synchronize()

    def _two_point(self, tp, d_raw, bufs, grid, stream):
        """Eq. (5) on the corrected frame in place: the test level per band (``"paper"``),
        its ratio to the flat's, the product; DQ already holds the flat's flags."""
        k = self.k
        ratio = tp["ones"]
        if tp["paper"]:
            bufs["tp_sums"].copy_to_device(bufs["tp_zero_f"], stream=stream)
            bufs["tp_counts"].copy_to_device(bufs["tp_zero_i"], stream=stream)
            k.band_sums[self._strided(grid), self.block, stream](
                d_raw, bufs["fdq"], tp["band"], bufs["tp_sums"], bufs["tp_counts"])
            k.two_point_ratio[1, k.MAX_BANDS, stream](bufs["tp_sums"], bufs["tp_counts"],
                                                      tp["flat_mean"], bufs["tp_ratio"])
            ratio = bufs["tp_ratio"]
        k.two_point_apply[grid, self.block, stream](bufs["frame"], bufs["fdq"], tp["gain"],
                                                    ratio, tp["band"])

    @staticmethod
    def _strided(grid):
        """A grid for the kernels that loop over rows (grid-stride): every column, at most
        64 blocks down (a block then flushes its partial sums once for many rows)."""
        return (grid[0], min(grid[1], 64))

    def _ppi(self, planes, bufs, medians, with_alpha, grid, stream):
        """PPID's band levels, pseudo-panchromatic image and (``with_alpha``) alpha window."""
        k = self.k
        k.band_levels[1, 1, stream](medians, bufs["levels"], bufs["inv_level"])
        k.ppi_values[grid, self.block, stream](bufs["frame"], bufs["fdq"], planes["band_of"],
                                              bufs["inv_level"], bufs["vals"], bufs["wts"])
        k.ppi_window[grid, self.block, stream](bufs["vals"], bufs["wts"], planes["rows"],
                                              planes["cols"], planes["kx"], planes["ky"],
                                              bufs["ppi"], bufs["ppi_ok"])
        if with_alpha:
            my, mx = planes["win"]
            k.window_max[grid, self.block, stream](bufs["alpha"], my, mx, bufs["alpha_win"])

    def _per_value(self, shape, n):
        """Grid and block of the kernels with one thread per value of an (H, W, n) cube:
        blocks of (n, pixels, rows) threads, about as many pixels as ``block`` has threads
        along the row (at least one), its rows down (fewer where n is large)."""
        H, W = shape
        bx, by = self.block
        px = max(1, bx // n)
        rows = max(1, min(by, 1024 // (n * px)))
        return ((W + px - 1) // px, (H + rows - 1) // rows), (n, px, rows)

    def _matrix(self, planes, bufs, mode, fold, with_alpha, stream):
        grid, block = self._per_value(bufs["frame"].shape, planes["n_virtual"])
        self.k.correction_matrix[grid, block, stream](
            bufs["cube"], bufs["cube_dq"], bufs["cube_alpha"], with_alpha, planes["coef"],
            planes["support"], mode, fold, bufs["out"], bufs["out_dq"], bufs["out_alpha"])

    def _medians(self, planes, bufs, stream, always=False):
        """The band medians of the corrected frame on the device (:func:`hsiffc.gpu.kernels.
        median_hist` ...), or None for more bands than the kernels take (then a cube with
        values to fill goes through :meth:`_fill`). Unless ``always``, the passes do nothing
        on a frame whose cube listed no value to fill."""
        k, B = self.k, planes["n_bands"]
        if B > k.MAX_BANDS:
            return None
        H, W = bufs["frame"].shape
        ph, pw = planes["period"]
        bx, by = self.block
        grid = self._strided(((W + bx - 1) // bx, (H + by - 1) // by))
        bits = bufs["frame"].view(np.uint32)
        need = planes["always"] if always else bufs["missing"]
        for n, shift in enumerate(k.DIGIT_SHIFTS):
            mask = (0xFFFFFFFF << (shift + 4)) & 0xFFFFFFFF
            k.median_hist[grid, self.block, stream](bits, bufs["fdq"], planes["phase_band"], ph,
                                                    pw, bufs["prefix"], mask, shift, n == 0,
                                                    bufs["hist"], need)
            k.median_select[B, 2, stream](bufs["hist"], bufs["prefix"], bufs["rank"],
                                          bufs["count"], shift, n == 0)
        k.median_finish[1, k.MAX_BANDS, stream](bufs["prefix"], bufs["count"],
                                                bufs["sel_bits"])
        k.median_mean[1, k.MAX_BANDS, stream](bufs["sel_bits"].view(np.float32),
                                              bufs["count"], bufs["medians"])
        return bufs["medians"]

    def _bilinear(self, planes, bufs, mode, fold, with_alpha, medians, stream):
        ph, pw = planes["period"]
        grid, block = self._per_value(bufs["frame"].shape, planes["n_bands"])
        ppid = planes["method"] == "ppid"
        oy, ox = planes["offset"]
        k = self.k
        k.bilinear[grid, block, stream](
            k.CubeIn(bufs["frame"], bufs["fdq"], True, bufs["alpha"], with_alpha),
            k.Lattices(planes["lat_r"], planes["lat_c"], planes["lat_start"], ph, pw,
                       planes["ymod"], planes["xmod"], planes["wy_of"], planes["wx_of"]),
            k.CubeOut(bufs["out"], bufs["out_dq"], bufs["out_alpha"], mode, fold),
            k.MedianFill(planes["no_medians"] if medians is None else medians,
                         medians is not None, bufs["missing"], bufs["miss_list"]),
            k.NearestTerms(planes["method"] == "nearest", planes["pat_r"], planes["pat_c"],
                           planes["pat_start"], oy, ox),
            k.PpidTerms(ppid, bufs["ppi"], bufs["ppi_ok"], bufs["levels"], bufs["alpha_win"]))

    def _host_fill(self, slot) -> bool:
        """Whether the cube has values to fill that the device did not: more than
        :data:`~hsiffc.gpu.kernels.MAX_BANDS` bands, or more values than its list holds."""
        n = int(slot["host"]["missing"][0])
        return n > 0 and (slot["planes"]["n_bands"] > self.k.MAX_BANDS
                          or n > slot["dev"]["miss_list"].shape[0])

    def _fill(self, slot):
        """A cube with values whose wide support has no usable sample: the band medians of
        the corrected frame (the CPU path's own :func:`~hsiffc.reconstruct.prepare.
        band_medians`), then the cube again with them (synchronous: such frames are rare)."""
        dev, host, st = slot["dev"], slot["host"], slot["stream"]
        planes, mos = slot["planes"], slot["mosaic"]
        frame = dev["frame"].copy_to_host(stream=st)
        fdq = dev["fdq"].copy_to_host(stream=st)
        st.synchronize()
        bands = np.flatnonzero(host["missing"][1:])
        meds = np.zeros(planes["n_bands"], np.float32)
        meds[bands] = band_medians(prepare(frame, mos, fdq), bands).astype(np.float32)
        d_meds = self.cuda.to_device(meds, stream=st)
        if "coef" in planes:
            cube = {**dev, "out": dev["cube"], "out_dq": dev["cube_dq"],
                    "out_alpha": dev["cube_alpha"]}
            self._bilinear(planes, cube, 0, False, slot["alpha"], d_meds, st)
            self._matrix(planes, dev, slot["mode"], slot["fold"], slot["alpha"], st)
        else:
            self._bilinear(planes, dev, slot["mode"], slot["fold"], slot["alpha"], d_meds, st)
        self._download(slot)
        st.synchronize()

    def _download(self, slot):
        dev, host, st = slot["dev"], slot["host"], slot["stream"]
        dev["out"].copy_to_host(host["out"], stream=st)
        dev["out_dq"].copy_to_host(host["out_dq"], stream=st)
        if slot["alpha"]:
            src = dev["out_alpha"] if self.rec is not None else dev["alpha"]
            src.copy_to_host(host["alpha"], stream=st)

    def _buffers(self, shape, planes, data_dtype, dq_dtype, with_alpha):
        cuda = self.cuda
        H, W = shape
        n_bands = planes.get("n_bands", 0)
        n_out = planes.get("n_virtual", n_bands)
        out_shape = (H, W) if self.rec is None else (H, W, n_out)
        a_shape = out_shape if (with_alpha and self.rec is not None) else (1, 1, 1)
        dev = {"frame": cuda.device_array(shape, np.float32),
               "alpha": cuda.device_array(shape, np.float32),
               "fdq": cuda.device_array(shape, DQ_DTYPE),
               "out": cuda.device_array(out_shape, data_dtype),
               "out_dq": cuda.device_array(out_shape, dq_dtype),
               "out_alpha": cuda.device_array(a_shape, np.float32),
               "missing": cuda.device_array(n_bands + 1, np.int64)}
        if "coef" in planes:  # the physical-band cube before the matrix
            dev.update(cube=cuda.device_array((H, W, n_bands), np.float32),
                       cube_dq=cuda.device_array((H, W, n_bands), DQ_DTYPE),
                       cube_alpha=cuda.device_array((H, W, n_bands) if with_alpha
                                                    else (1, 1, 1), np.float32))
        empty = cuda.pinned_array
        tp = planes.get("two_point")
        if tp is not None and tp["paper"]:
            n = tp["n"]
            dev.update(tp_sums=cuda.device_array(n, np.float64),
                       tp_counts=cuda.device_array(n, np.int64),
                       tp_ratio=cuda.device_array(n, np.float32),
                       tp_zero_f=_pinned_zeros(cuda, n, np.float64),
                       tp_zero_i=_pinned_zeros(cuda, n, np.int64))
        ppid = planes.get("method") == "ppid"
        dev.update(ppi=cuda.device_array(shape if ppid else (1, 1), np.float32),
                   ppi_ok=cuda.device_array(shape if ppid else (1, 1), np.uint8),
                   vals=cuda.device_array(shape if ppid else (1, 1), np.float32),
                   wts=cuda.device_array(shape if ppid else (1, 1), np.float32),
                   alpha_win=cuda.device_array(shape if ppid and with_alpha else (1, 1),
                                               np.float32),
                   levels=cuda.device_array(max(n_bands, 1), np.float64),
                   inv_level=cuda.device_array(max(n_bands, 1), np.float32),
                   zeros=_pinned_zeros(cuda, n_bands + 1, np.int64),
                   miss_list=cuda.device_array(max(1024, H * W // 8) if self.rec is not None
                                               else 1, np.int64))
        if self.rec is not None:
            nb = max(n_bands, 1)
            dev.update(hist=cuda.to_device(np.zeros((nb, 2, 16), np.int32)),
                       prefix=cuda.device_array((nb, 2), np.uint32),
                       rank=cuda.device_array((nb, 2), np.int64),
                       count=cuda.device_array(nb, np.int64),
                       sel_bits=cuda.device_array((nb, 2), np.uint32),
                       medians=cuda.device_array(nb, np.float32))
        host = {"out": empty(out_shape, data_dtype), "out_dq": empty(out_shape, dq_dtype),
                "missing": empty(n_bands + 1, np.int64),
                "alpha": empty(a_shape if self.rec is not None else
                               (shape if with_alpha else (1, 1)), np.float32)}
        return dev, host

    def _meta(self, meta, exposure_ms, how):
        """The metadata the CPU pipeline gives the frame (history of every step)."""
        meta = dict(meta)
        hist = list(meta.get("history", ()))
        meta["dark_source"] = how
        hist.append(_entry(*self.dark))
        meta["alpha_threshold_percent"] = float(self.mask[1].threshold_percent)
        hist.append(_entry(*self.mask))
        if self.ffc is not None:
            ffc = self.ffc[1]
            if ffc.gpu_as == "two_point_ffc":
                meta.update(ffc="two_point", ffc_training_ms=ffc.selected_ms_)
            else:
                meta["ffc"] = "model"
            hist.append(_entry(*self.ffc))
        if self.rec is not None:
            meta.update(self._rec_meta(meta.get("mosaic"), meta.get("bit_depth", 16)))
            hist.append(_entry(*self.rec))
        meta["history"] = tuple(hist)
        return meta

    def _rec_meta(self, mosaic, bit_depth):
        """What the reconstruct stage adds to a frame's metadata (wavelengths, band positions
        ...): the stage's own ``transform`` on a frame of two tiles of this mosaic, kept per
        mosaic (it depends on nothing else at full resolution)."""
        cache = self._rec_meta_cache
        key = mosaic  # hashed and compared by value (pattern, wavelengths, offset)
        if key not in cache:
            ph, pw = (int(v) for v in mosaic.tile_shape)
            stub = Frame(np.zeros((2 * ph, 2 * pw), np.float32),
                         np.zeros((2 * ph, 2 * pw), DQ_DTYPE),
                         {"exposure_ms": 1.0, "bit_depth": int(bit_depth), "mosaic": mosaic})
            before = set(stub.meta)
            done = self.rec[1].transform(stub).meta
            cache[key] = (mosaic, {k: v for k, v in done.items()
                                   if k not in before or k in ("wavelengths_nm",)})
        return dict(cache[key][1])

    def transform(self, frame: Frame) -> Frame:
        """The CPU pipeline's frame for ``frame``, computed on the GPU."""
        item, done = next(iter(self._run([frame], {"alpha": True, "copy": True},
                                         self._transform_slots)))
        if done is not None:
            return done
        return Frame(item.data, item.dq, item.meta, alpha=item.alpha,
                     dark_removed=self._last_dark,
                     corrected_by=self.ffc[1].name if self.ffc is not None else None)

    # -- the live stream ------------------------------------------------------------------------
    def stream(self, frames, *, exposure_ms=None, bit_depth=None, mosaic=None,
               data_dtype: str = "float32", dq_dtype: str = "uint32", alpha: bool = False,
               copy: bool = True):
        """Correct ``frames`` (an iterable of :class:`~hsiffc.data.frame.Frame` or of raw 2-D
        arrays, which then need ``exposure_ms``, ``bit_depth`` and, for a cube, ``mosaic``)
        and yield one :class:`StreamItem` per frame, in order.

        Two slots, each with its CUDA stream, pinned host buffers and device buffers: frame
        ``i`` is uploaded, corrected and downloaded on one slot while the caller works on
        frame ``i - 1`` from the other. ``copy=False`` yields views of the pinned buffers,
        valid until the item after next is asked for (no host copy: the fastest); the default
        copies. ``data_dtype`` / ``dq_dtype``: :mod:`hsiffc.gpu.pack`. ``alpha``: also the
        alpha plane or cube (float32; costs its copy).
        """
        opts = {"exposure_ms": exposure_ms, "bit_depth": bit_depth, "mosaic": mosaic,
                "data_dtype": data_dtype, "dq_dtype": dq_dtype, "alpha": alpha, "copy": copy}
        for item, _ in self._run(frames, opts):
            yield item

    def _run(self, frames, opts, slots=None):
        """:meth:`stream`'s items, each with the CPU pipeline's frame where that made it
        (``slots``: buffers to reuse, from an earlier call)."""
        exposure_ms, bit_depth, mosaic = (opts.get(k) for k in ("exposure_ms", "bit_depth",
                                                                  "mosaic"))
        alpha, copy = bool(opts.get("alpha", False)), bool(opts.get("copy", True))
        data_dtype, dq_dtype = check_dtypes(opts.get("data_dtype", "float32"),
                                            opts.get("dq_dtype", "uint32"))
        mode, fold = DATA_DTYPES.index(data_dtype), dq_dtype == "uint8"
        cuda = self.cuda
        slots = [None, None] if slots is None else slots
        pending = [None, None]
        i = 0
        for item in frames:
            s = i % 2
            if pending[s] is not None:
                yield self._finish(pending[s], copy)
                pending[s] = None
            if isinstance(item, Frame):
                raw, dq_in, exp, bd, mos, meta = (item.data, item.dq, item.exposure_ms,
                                                  item.bit_depth, item.mosaic, dict(item.meta))
            else:
                raw, dq_in = np.asarray(item), None
                if exposure_ms is None or bit_depth is None:
                    raise ParameterError("stream of raw arrays: give exposure_ms= and "
                                         "bit_depth= (and mosaic= for a cube)")
                exp, bd, mos = float(exposure_ms), int(bit_depth), mosaic
                meta = {"exposure_ms": exp, "bit_depth": bd, "mosaic": mos, "kind": "light"}
            if exp == 0 or raw.ndim != 2:  # the CPU pipeline's own case
                pending[s] = _Pending("cpu", item, raw, exp, bd, mos, meta,
                                      (data_dtype, dq_dtype, alpha))
                i += 1
                continue
            key = (raw.shape, raw.dtype.str, dq_in is not None, data_dtype, dq_dtype, alpha,
                   mos)
            slot = slots[s]
            if slot is None or slot["key"] != key:
                planes, _ = self._const(raw.shape, exp, bd, mos)
                dev, host = self._buffers(raw.shape, planes, data_dtype, dq_dtype, alpha)
                slot = {"key": key, "alpha": alpha, "planes": planes, "mosaic": mos,
                        "mode": mode, "fold": fold, "dev": dev, "host": host, "stream": cuda.stream(),
                        "pin_raw": cuda.pinned_array(raw.shape, raw.dtype),
                        "d_raw": cuda.device_array(raw.shape, raw.dtype),
                        "pin_dq": cuda.pinned_array(raw.shape, DQ_DTYPE) if dq_in is not None
                        else None,
                        "d_dq": cuda.device_array(raw.shape if dq_in is not None else (1, 1),
                                                  DQ_DTYPE)}
                slots[s] = slot
            st = slot["stream"]
            np.copyto(slot["pin_raw"], raw)
            slot["d_raw"].copy_to_device(slot["pin_raw"], stream=st)
            if dq_in is not None:
                np.copyto(slot["pin_dq"], dq_in)
                slot["d_dq"].copy_to_device(slot["pin_dq"], stream=st)
            dev, host = slot["dev"], slot["host"]
            self._launch(DeviceFrame(slot["d_raw"], slot["d_dq"], dq_in is not None, raw.shape,
                                     exp, bd, mos), dev, OutputTypes(mode, fold, alpha), st)
            self._download(slot)
            if self.rec is not None:
                dev["missing"].copy_to_host(host["missing"], stream=st)
            _, (_, how, plane) = self._const(raw.shape, exp, bd, mos)
            self._last_dark = plane
            pending[s] = _Pending("gpu", item, raw, exp, bd, mos, self._meta(meta, exp, how),
                                  slot)
            i += 1
        for k in range(2):
            s = (i + k) % 2
            if pending[s] is not None:
                yield self._finish(pending[s], copy)

    def _finish(self, pending: _Pending, copy):
        where, item, raw, exp, bd, mos, meta, slot = pending
        if where == "gpu":
            slot["stream"].synchronize()
            host = slot["host"]
            if self.rec is not None and self._host_fill(slot):
                self._fill(slot)
            elif self.rec is not None and int(host["missing"][0]):
                self._fill_device(slot)
            pick = (lambda a: a.copy()) if copy else (lambda a: a)
            alpha = pick(host["alpha"]) if slot["alpha"] else None
            return StreamItem(pick(host["out"]), pick(host["out_dq"]), alpha, meta), None
        dtypes = slot
        frame = item if isinstance(item, Frame) else Frame.from_raw(
            raw, exposure_ms=exp, bit_depth=bd, mosaic=mos)
        done = self.pipeline.transform(frame)
        data, dq = pack_cpu(done.data, done.dq, dtypes[0], dtypes[1])
        alpha = None if not dtypes[2] or done.alpha is None else np.asarray(done.alpha)
        return StreamItem(data, dq, alpha, dict(done.meta)), done


def cpu_stream(pipeline, frames, *, exposure_ms=None, bit_depth=None, mosaic=None,
               data_dtype: str = "float32", dq_dtype: str = "uint32", alpha: bool = False,
               copy: bool = True):
    """:meth:`GpuPipeline.stream` on the CPU: a plain loop over ``pipeline.transform``, the
    output in the same types (``copy`` has nothing to share and is ignored)."""
    data_dtype, dq_dtype = check_dtypes(data_dtype, dq_dtype)
    for item in frames:
        if not isinstance(item, Frame):
            if exposure_ms is None or bit_depth is None:
                raise ParameterError("stream of raw arrays: give exposure_ms= and bit_depth= "
                                     "(and mosaic= for a cube)")
            item = Frame.from_raw(np.asarray(item), exposure_ms=float(exposure_ms),
                                  bit_depth=int(bit_depth), mosaic=mosaic)
        done = pipeline.transform(item)
        data, dq = pack_cpu(done.data, done.dq, data_dtype, dq_dtype)
        a = None if not alpha or done.alpha is None else np.asarray(done.alpha)
        yield StreamItem(data, dq, a, dict(done.meta))
