"""The in-memory exposure sweep: a stack of raw frames with one row of metadata per frame.

Frames are kept in acquisition order. Every per-frame field is a 1-D array of length
``n_frames``, so sweeps with a different number of frames per step (EMVA 1288's 2-frame sweep
steps and 100-frame spatial sets) fit in one object.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from .mosaic import Mosaic

FRAME_KINDS = ("light", "dark")


@dataclass(frozen=True, eq=False)
class Sweep:
    """Raw frames and their per-frame metadata.

    Parameters
    ----------
    data : (N, H, W) array
        Raw counts in DN, as read (integer or float; never rescaled).
    exposure_ms : (N,) float
        Exposure time of each frame in milliseconds.
    kind : (N,) str
        ``"light"`` or ``"dark"``.
    step : (N,) int, optional
        Acquisition step each frame belongs to (frames of one step share exposure and light).
        Default: consecutive frames with equal exposure, kind and illumination share a step.
    photons : (N,) float, optional
        Mean photons per pixel during the frame (EMVA 1288); NaN where unknown.
    illumination : (N,) str, optional
        Illumination label of each frame ("2900K", "lamp A", ...); "" for darks.
    bit_depth : int
        ADC bit depth; full scale is ``2**bit_depth - 1`` DN.
    mosaic : Mosaic, optional
    source : str
        Where the frames came from (file path or "simulated").
    meta : dict
        Anything else (JSON-serialisable), e.g. the simulator's settings or the descriptor header.

    Examples
    --------
    Two dark and two light frames of 2 x 3 pixels, read with a 12-bit ADC:

    >>> import numpy as np
    >>> from hsiffc import Sweep
    >>> frames = np.arange(24, dtype=np.uint16).reshape(4, 2, 3) + 100
    >>> sweep = Sweep(frames, exposure_ms=[10, 10, 20, 20],
    ...               kind=["dark", "dark", "light", "light"], bit_depth=12)
    >>> sweep.n_frames, sweep.frame_shape, sweep.full_scale_dn
    (4, (2, 3), 4095)
    >>> sweep.step.tolist()                  # consecutive frames with equal settings
    [0, 0, 1, 1]
    >>> sweep.light().exposure_ms.tolist()
    [20.0, 20.0]
    >>> print(sweep.summary())
    4 frames (2 light, 2 dark) of 2 x 3 px, 12-bit, 2 steps, exposure 10-20 ms
    >>> sweep                                # key figures, never the array
    <Sweep 4 frames of 2 x 3 px uint16, 12-bit, 2 steps, exposure 10-20 ms, 2 light + 2 dark>
    """

    data: np.ndarray
    exposure_ms: np.ndarray
    kind: np.ndarray
    bit_depth: int
    step: np.ndarray | None = None
    photons: np.ndarray | None = None
    illumination: np.ndarray | None = None
    mosaic: Mosaic | None = None
    source: str = ""
    meta: dict = field(default_factory=dict)

    def __post_init__(self):
        data = np.asarray(self.data)
        if data.ndim == 2:
            data = data[None]
        if data.ndim != 3:
            raise ValueError(f"data must be (N, H, W) frames, got shape {data.shape}")
        n = data.shape[0]

        def per_frame(name, value, dtype, default):
            if value is None:
                value = default
            arr = np.asarray(value, dtype=dtype)
            if arr.ndim == 0:
                arr = np.full(n, arr, dtype=dtype)
            if arr.shape != (n,):
                raise ValueError(f"{name} must have one entry per frame ({n}), got shape {arr.shape}")
            return arr

        exposure = per_frame("exposure_ms", self.exposure_ms, np.float64, None)
        if not np.all(np.isfinite(exposure)) or np.any(exposure < 0):
            bad = np.flatnonzero(~np.isfinite(exposure) | (exposure < 0))
            raise ValueError(f"exposure_ms must be finite and >= 0; frames {bad.tolist()} are not")
        kind = per_frame("kind", self.kind, object, None)
        bad_kind = [k for k in set(kind.tolist()) if k not in FRAME_KINDS]
        if bad_kind:
            raise ValueError(f"kind must be one of {FRAME_KINDS}, got {bad_kind}")
        kind = kind.astype("U5")
        illum = per_frame("illumination", self.illumination, object, "").astype(str)
        photons = per_frame("photons", self.photons, np.float64, np.nan)
        if self.step is None:
            key = list(zip(exposure.tolist(), kind.tolist(), illum.tolist(), photons.tolist()))
            step = np.zeros(n, dtype=np.int64)
            for i in range(1, n):
                same = key[i] == key[i - 1] or (
                    key[i][:3] == key[i - 1][:3] and np.isnan(key[i][3]) and np.isnan(key[i - 1][3]))
                step[i] = step[i - 1] + (0 if same else 1)
        else:
            step = per_frame("step", self.step, np.int64, None)
        if int(self.bit_depth) < 1 or int(self.bit_depth) > 32:
            raise ValueError(f"bit_depth must be 1..32, got {self.bit_depth}")
        for name, value in (("data", data), ("exposure_ms", exposure), ("kind", kind),
                            ("illumination", illum), ("photons", photons), ("step", step)):
            object.__setattr__(self, name, value)
        object.__setattr__(self, "bit_depth", int(self.bit_depth))

    def __repr__(self) -> str:  # key figures, never the arrays
        n, h, w = self.data.shape
        t = self.exposure_ms
        parts = [f"{n} frames of {h} x {w} px {self.data.dtype}", f"{self.bit_depth}-bit",
                 f"{len(np.unique(self.step))} steps"]
        if n:
            parts.append(f"exposure {t.min():.4g}-{t.max():.4g} ms")
        parts.append(" + ".join(f"{int(np.count_nonzero(self.kind == k))} {k}"
                                for k in FRAME_KINDS))
        if self.mosaic is not None:
            parts.append(f"mosaic {self.mosaic.describe()}")
        if self.source:
            parts.append(f"from {self.source}")
        return f"<Sweep {', '.join(parts)}>"

    # -- basic facts ---------------------------------------------------------------------------
    @property
    def n_frames(self) -> int:
        """Number of frames N."""
        return int(self.data.shape[0])

    @property
    def frame_shape(self) -> tuple[int, int]:
        """Frame shape (H, W) in pixels."""
        return tuple(int(s) for s in self.data.shape[1:])

    @property
    def full_scale_dn(self) -> int:
        """Full scale ``2**bit_depth - 1`` (DN)."""
        return 2 ** self.bit_depth - 1

    @property
    def order(self) -> np.ndarray:
        """Acquisition order (frames are stored in it)."""
        return np.arange(self.n_frames)

    @property
    def is_light(self) -> np.ndarray:
        """(N,) bool: light frames."""
        return self.kind == "light"

    @property
    def is_dark(self) -> np.ndarray:
        """(N,) bool: dark frames."""
        return self.kind == "dark"

    def light_rate_relative(self) -> np.ndarray:
        """photons / exposure per frame (photons per pixel per ms), NaN where unknown or t = 0.

        In EMVA 1288 data the irradiance changes from step to step; the light rate k of a pixel in
        a step is proportional to this number.
        """
        with np.errstate(divide="ignore", invalid="ignore"):
            rate = self.photons / self.exposure_ms
        rate[~np.isfinite(rate)] = np.nan
        return rate

    # -- selection -----------------------------------------------------------------------------
    def select(self, index) -> "Sweep":
        """A new sweep with the frames picked by a boolean mask or index array."""
        idx = np.arange(self.n_frames)[index]
        return replace(self, data=self.data[idx], exposure_ms=self.exposure_ms[idx],
                       kind=self.kind[idx], step=self.step[idx], photons=self.photons[idx],
                       illumination=self.illumination[idx])

    def light(self) -> "Sweep":
        """The light frames as a new Sweep."""
        return self.select(self.is_light)

    def dark(self) -> "Sweep":
        """The dark frames as a new Sweep."""
        return self.select(self.is_dark)

    def steps(self) -> np.ndarray:
        """Step ids in acquisition order."""
        _, first = np.unique(self.step, return_index=True)
        return self.step[np.sort(first)]

    def step_means(self, dtype=np.float64):
        """Mean frame of every step, with its exposure, kind, photons and frame count.

        Returns
        -------
        dict with ``data`` (S, H, W) and per-step arrays ``exposure_ms``, ``kind``, ``photons``,
        ``illumination``, ``n_frames``, ``step``.
        """
        steps = self.steps()
        out = np.empty((len(steps),) + self.frame_shape, dtype=dtype)
        first = np.empty(len(steps), dtype=np.int64)
        counts = np.empty(len(steps), dtype=np.int64)
        for i, s in enumerate(steps):
            sel = np.flatnonzero(self.step == s)
            out[i] = self.data[sel].mean(axis=0, dtype=dtype)
            first[i] = sel[0]
            counts[i] = sel.size
        return {"data": out, "exposure_ms": self.exposure_ms[first], "kind": self.kind[first],
                "photons": self.photons[first], "illumination": self.illumination[first],
                "n_frames": counts, "step": steps}

    def summary(self) -> str:
        """A short human-readable description."""
        light, dark = int(self.is_light.sum()), int(self.is_dark.sum())
        t = self.exposure_ms
        mos = f", mosaic {self.mosaic.describe()}" if self.mosaic else ""
        return (f"{self.n_frames} frames ({light} light, {dark} dark) of "
                f"{self.frame_shape[0]} x {self.frame_shape[1]} px, {self.bit_depth}-bit{mos}, "
                f"{len(self.steps())} steps, exposure {t.min():.4g}-{t.max():.4g} ms"
                + (f", from {self.source}" if self.source else ""))
