"""EMVA 1288 Release 4.0 characterisation of a sweep, as the standard's reference
implementation computes it, plus what the leakage model says about the figures.

- :func:`characterise` (:mod:`.compute`): the standard's figures under the reference
  implementation's names (``K``, ``R``, ``QE``, ``sigma_y_dark``, ..., ``u_I_var``), with units,
  fit ranges and standard errors; per band of a mosaic.
- :func:`leakage_effects` (:mod:`.leakage`): beyond the standard, what a per-pixel leakage
  calibration says about them (share of the linearity error it explains, dynamic saturation
  against light rate, alpha at the standard's saturation point, leakage in the saturation
  capacity).
- :func:`write_report` (:mod:`.render`, :mod:`.plot`): the standard's plots as PNG and a
  Markdown page with the figures table.
- :func:`hsiffc.emva1288.general.general_figures` (:mod:`.general`): Release 4.0 General, the
  application figures without the linear model (differential responsivity, SNR, saturation,
  threshold, dynamic range), measured and as the leakage model predicts them.
- :func:`run_characterisation`: all of it for one measurement.
- :mod:`.agreement`: the figures of the shared EMVA 1288 sets beside the reference
  implementation's (``python3 -m hsiffc.emva1288 DATA OUTDIR``).
"""

from __future__ import annotations

from .compute import FIGURES, characterise, saturation_index, step_statistics
from .render import render_markdown, to_json, write_report  # matplotlib loads when plotting

__all__ = ["FIGURES", "LEAKAGE_PIXELS", "characterise", "leakage_effects", "leakage_pixels",
           "render_markdown", "run_characterisation", "saturation_index", "step_mean_sweep",
           "step_statistics", "to_json", "write_report"]

#: Pixels the leakage account of :func:`run_characterisation` calibrates and evaluates (drawn
#: at random, seed :data:`LEAKAGE_SEED`; all of a smaller sensor). Its figures are means,
#: percentiles and shares over pixels; on the shared CMOS set (32768 pixels) 8192 pixels give
#: them within a small sampling spread of the all-pixel values (five seeds: the share of the
#: linearity error explained 14.23 +- 0.09 % against 14.28 %, the median alpha at saturation
#: 4.83 +- 0.04 % against 4.83 %, the leaked share 0.493 +- 0.003 % against 0.495 %, the
#: predicted saturation step the same), and the time no longer grows with the sensor.
LEAKAGE_PIXELS = 8192
LEAKAGE_SEED = 0
#: Pixels of the calibration's pilot (its sensor-wide start values of b and of the saturation
#: margin, medians over these pixels; ``pilot_pixels`` of :func:`hsiffc.calibrate.calibrate_joint`)
#: in the leakage account: a quarter of the drawn pixels. Against the calibration's default
#: (4096) on the shared CMOS set, the account's figures move by at most 0.002 percentage points
#: (explained share 14.236 against 14.234 %, median alpha 4.8376 against 4.8375 %) and its fit
#: takes 0.29 instead of 0.46 s of CPU.
LEAKAGE_PILOT_PIXELS = 2048


def __getattr__(name):
    """:func:`leakage_effects` loads the leakage model (and numba) when first named: the
    figures alone (``hsiffc emva1288 --no-leakage``) of a small set never load numba."""
    if name == "leakage_effects":
        from .leakage import leakage_effects

        return leakage_effects
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def leakage_pixels(frame_shape, n=LEAKAGE_PIXELS, seed=LEAKAGE_SEED):
    """The pixels (sorted flat indices) the leakage account uses: ``n`` drawn at random
    without replacement with ``seed``, or None (all) when the frame has at most ``n`` or ``n``
    is None."""
    import numpy as np

    total = int(np.prod(frame_shape))
    if n is None or total <= n:
        return None
    return np.sort(np.random.default_rng(seed).choice(total, int(n), replace=False))


def step_mean_sweep(stats: dict, source) -> tuple:
    """The sweep steps of :func:`step_statistics` (``keep_step_means=True``, or given pixels)
    as a Sweep of one float32 frame per step (its per-pixel mean; full scale where some frame of
    the step was, so that the calibration sees it clipped), each standing for the step's frames
    (``meta["frames_averaged"]``), and the photon transfer of the raw frames' first pairs. At
    given pixels the frames are (1, N), without the mosaic.

    Returns
    -------
    sweep : Sweep
        What :func:`hsiffc.calibrate.calibrate` fits the leakage model on.
    ptc : PhotonTransfer or None
        Its ``ptc`` argument.
    """
    import numpy as np

    from ..calibrate.samples import photon_transfer_from_pairs
    from ..data.sweep import Sweep

    info = stats["sweep_step_info"]
    pairs = [(k, p[0], p[1] / p[0] if p[0] else np.nan, 0.5 * p[2] / p[0] if p[0] else np.nan)
             for k, p, n in zip(info["kind"], stats["pairs"], info["n_frames"]) if n >= 2]
    ptc = photon_transfer_from_pairs(pairs, stats["n_pixels"], stats["full_scale_dn"])
    label = getattr(source, "source", None) or getattr(source, "label", "") or ""
    whole = stats.get("step_mean_pixels") is None
    sweep = Sweep(stats["step_means"], info["exposure_ms"], info["kind"].astype(str),
                  stats["bit_depth"], step=info["step"], photons=info["photons"],
                  mosaic=getattr(source, "mosaic", None) if whole else None, source=str(label),
                  meta={"frames_averaged": info["n_frames"]})
    return sweep, ptc


def _warm_leakage_code() -> None:
    """Import the calibration and the leakage model, and load their compiled code once from
    numba's cache (its first load in a process sets numba up: most of the time a later load
    takes)."""
    try:
        from .. import calibrate  # noqa: F401  (numba and the calibration's modules)
        from ..leakage import model
        from . import leakage  # noqa: F401

        model.response(1.0, 1.0, 0.0, 0.01, 0.0)
    except Exception:  # the same imports in the caller raise what is wrong
        pass


def _leakage_account(stats, source, res):
    """The leakage model's account of a sweep from the step means in its statistics
    (:func:`step_mean_sweep`): ``(leak, None)``, or ``(None, note)`` where the sweep cannot
    calibrate the leakage model."""
    from ..calibrate import LEAKAGE_ACCOUNT, calibrate
    from ..errors import DataFormatError
    from .leakage import leakage_effects

    means, ptc = step_mean_sweep(stats, source)
    try:
        # the leakage model's own account (no held-out choice of a simpler model)
        calibration = calibrate(means, method="joint", ptc=ptc, pilot_pixels=LEAKAGE_PILOT_PIXELS,
                                **LEAKAGE_ACCOUNT)
    except DataFormatError as exc:
        return None, f"not computed: the sweep cannot calibrate the leakage model ({exc})"
    return leakage_effects(means, res, calibration), None


def _account_worker(conn) -> None:
    """A child process: loads the leakage code while the parent reads the frames and says so
    ("ready"), then computes :func:`_leakage_account` of what the parent sends (None: nothing
    to do) and sends it with the warnings it gave (the parent issues them under its own
    filters).

    The child collects no cyclic garbage: it lives for one account, and the collections that
    loading numba set off (each walking every object of the modules loaded, and the parent's
    objects it shares, which copies their pages) were 0.24 s of its 1.85 s of CPU (median of
    six runs of the loading alone, at load 5)."""
    import gc
    import warnings

    gc.disable()
    try:
        _warm_leakage_code()
        conn.send("ready")
        job = conn.recv()
        if job is not None:
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                out = _leakage_account(*job)
            conn.send((out, [(w.message, w.category, w.filename, w.lineno) for w in caught]))
    except BaseException:  # noqa: BLE001  the parent computes it again and raises what fails
        try:
            conn.send(None)
        except (OSError, ValueError):
            pass
    finally:
        conn.close()


class _AccountProcess:
    """The leakage account on the second core: a forked child (started before the frames are
    read) loads numba (1.1-1.4 s of CPU on its first use in a process) and the calibration
    while the parent reads, then fits the step means the parent sends. Where the platform
    cannot fork, where this process has loaded numba already (its start is paid, and numba's
    OpenMP threads, once started, make a forked child that uses them abort), or where the child
    fails, dies or is not ready within :attr:`READY_S`, :meth:`result` computes the account in
    this process."""

    READY_S = 300.0  # s: the child's imports take about a second; past this it is stuck

    def __init__(self, fork: bool = True):
        import multiprocessing as mp
        import sys
        import warnings

        self.proc = self.conn = None
        if (not fork or "numba" in sys.modules or sys.platform != "linux"
                or "fork" not in mp.get_all_start_methods()):
            return
        try:
            for stream in (sys.stdout, sys.stderr):  # a forked child must not write them again
                if stream is not None:
                    stream.flush()
            ctx = mp.get_context("fork")
            self.conn, child = ctx.Pipe()
            self.proc = ctx.Process(target=_account_worker, args=(child,), daemon=True,
                                    name="hsiffc-leakage-account")
            with warnings.catch_warnings():
                # Python 3.12+ warns on fork wherever a library has started threads (numpy's
                # BLAS pool): the child uses none of them, only numpy and hsiffc's own code
                warnings.filterwarnings("ignore", category=DeprecationWarning,
                                        message=".*fork")
                self.proc.start()
            child.close()
        except (OSError, ValueError):
            self.proc = self.conn = None

    def _receive(self, timeout=None):
        """The child's next message; None where it died, failed or took over ``timeout``."""
        import time

        end = None if timeout is None else time.monotonic() + timeout
        while self.proc.is_alive() or self.conn.poll(0):
            if self.conn.poll(0.05):
                try:
                    return self.conn.recv()
                except (OSError, EOFError):
                    return None
            if end is not None and time.monotonic() > end:
                return None
        return None

    def result(self, stats, source, res):
        """:func:`_leakage_account` of ``stats`` (only what :func:`step_mean_sweep` reads is
        sent), of ``source`` (its label and mosaic) and of ``res``."""
        import types

        stats = {k: stats.get(k) for k in ("sweep_step_info", "pairs", "n_pixels",
                                           "full_scale_dn", "step_means", "step_mean_pixels",
                                           "bit_depth")}
        label = getattr(source, "source", None) or getattr(source, "label", "") or ""
        source = types.SimpleNamespace(source=str(label), mosaic=getattr(source, "mosaic", None))
        sent = None
        if self.proc is not None:
            if self._receive(self.READY_S) == "ready":
                try:
                    self.conn.send((stats, source, res))
                    sent = self._receive()
                except (OSError, ValueError):
                    sent = None
            self.close()
        if sent is None:
            return _leakage_account(stats, source, res)
        import warnings

        out, caught = sent
        for message, category, filename, lineno in caught:
            warnings.warn_explicit(message, category, filename, lineno)
        return out

    def close(self):
        """End the child: told there is nothing to do, or killed where it does not listen."""
        if self.proc is None:
            return
        try:
            self.conn.send(None)
        except (OSError, ValueError):
            pass
        self.proc.join(5.0)
        if self.proc.is_alive():
            self.proc.kill()
            self.proc.join()
        self.conn.close()
        self.proc = None


def run_characterisation(sweep, *, pixel_area_um2=None, wavelength_nm=None, leakage=True,
                         calibration=None, n_leakage_pixels=LEAKAGE_PIXELS, background=True
                         ) -> tuple[dict, dict | None, str | None]:
    """The EMVA 1288 figures of ``sweep`` and, with ``leakage``, the leakage model's account.

    The frames are read once, one at a time (:mod:`.stream`): memory holds a few frames, the
    stacks' images and, for the leakage calibration, the means of every sweep step at
    ``n_leakage_pixels`` pixels (:func:`leakage_pixels`).

    Parameters
    ----------
    sweep : Sweep or FrameSource
        An EMVA 1288 measurement (:func:`hsiffc.io.read_emva1288`, or
        :func:`hsiffc.io.open_source` on its descriptor to stream it).
    pixel_area_um2, wavelength_nm : float, optional
        See :func:`characterise`.
    leakage : bool
        Also :func:`leakage_effects` (calibrates the sweep steps' means with
        :func:`hsiffc.calibrate.calibrate` unless ``calibration`` is given).
    calibration : Calibration, optional
        Leakage-model calibration of this measurement (every pixel is then used).
    n_leakage_pixels : int or None
        Pixels the leakage calibration fits and the account evaluates (:data:`LEAKAGE_PIXELS`,
        drawn with :data:`LEAKAGE_SEED`); None: every pixel.
    background : bool
        Calibrate and account in a child process forked before the frames are read (Linux,
        where this process has not loaded numba yet), so that loading numba (1.1-1.4 s of CPU
        the first time in a process) and the calibration runs on another core while this one
        reads; the same figures as False (all in this process, as on platforms that
        cannot fork, or if the child fails).

    Returns
    -------
    res : dict
        :func:`characterise`.
    leak : dict or None
        :func:`leakage_effects`, or None.
    note : str or None
        Why ``leak`` is None when ``leakage`` was asked for (the sweep cannot be calibrated).
    """
    keep = leakage and calibration is None
    pixels = leakage_pixels(sweep.frame_shape, n_leakage_pixels) if keep else None
    worker = _AccountProcess(background) if keep else None
    try:
        stats = step_statistics(sweep, keep_step_means=keep if pixels is None else pixels)
        res = characterise(sweep, pixel_area_um2=pixel_area_um2, wavelength_nm=wavelength_nm,
                           statistics=stats)
        if not leakage:
            return res, None, None
        from .general import general_figures

        if calibration is None:
            leak, note = worker.result(stats, sweep, res)
            del stats
            if leak is None:
                return res, None, note
        else:
            from .leakage import leakage_effects

            leak = leakage_effects(sweep, res, calibration)
    finally:
        if worker is not None:
            worker.close()
    h, w = sweep.frame_shape
    leak["calibration"].update(sensor_pixels=int(h * w),
                               drawn_seed=None if pixels is None else LEAKAGE_SEED)
    res["general"] = general_figures(res, leak)  # the model's General figures beside
    return res, leak, None
