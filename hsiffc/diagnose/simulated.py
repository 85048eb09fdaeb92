"""Simulated sweeps of the designs users bring (for tests, the docs and the benchmark), and a
writer of the EMVA 1288 format (descriptor + PNG images, as :func:`hsiffc.io.read_emva1288`
reads it).

Designs (``design=``):

- ``"mixed"``: light steps whose exposure (2-200 ms, shuffled) and light level both change, as
  in an EMVA 1288 sweep with a changing lamp; acquisition order and exposure are not confounded;
- ``"exposure"``: an exposure sweep (2-200 ms, increasing) at one light level;
- ``"light"``: a light sweep at one fixed exposure (20 ms), levels increasing (EMVA 1288 allows
  it; its reference simulations use it).

Each light step is followed by a dark step at the same exposure when ``darks`` is true.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..files.atomic import atomic_path, atomic_write_text
from ..simulate import PAPER_LIGHT_W_M2, MosaicSensor, SensorParams
from ..data.sweep import Sweep

DESIGNS = ("mixed", "exposure", "light")


def design_steps(design: str, n_steps: int, seed: int):
    """Exposures (ms) and relative light levels of the light steps of a design.

    Parameters
    ----------
    design : {"mixed", "exposure", "light"}
        Shuffled exposures with changing light, an exposure sweep at one light level, or a
        light sweep at one exposure.
    n_steps : int
        Light steps.
    seed : int
        Seed of the random choices.

    Returns
    -------
    exposure_ms : ndarray, (n_steps,), ms
    levels : ndarray, (n_steps,)
        Relative light level of each step (1 = the given irradiance).

    Raises
    ------
    ValueError
        Unknown design.

    Examples
    --------
    >>> t, levels = design_steps("exposure", 3, seed=0)
    >>> t.tolist(), levels.tolist()
    ([2.0, 20.0, 200.0], [0.25, 0.25, 0.25])
    """
    rng = np.random.default_rng(seed)
    if design == "mixed":
        t = rng.permutation(np.round(np.geomspace(2, 200, n_steps), 3))
        return t, np.exp(rng.uniform(np.log(0.15), 0.0, n_steps))
    if design == "exposure":
        return np.round(np.geomspace(2, 200, n_steps), 3), np.full(n_steps, 0.25)
    if design == "light":
        return np.full(n_steps, 20.0), np.linspace(0.02, 1.0, n_steps)
    raise ValueError(f"unknown design {design!r}; choose one of {DESIGNS}")


def simulated_sweep(design: str = "mixed", *, shape=(24, 32), n_steps: int = 40,
                    n_frames: int = 2, darks: bool = True, seed: int = 1, irradiance=None,
                    **params) -> Sweep:
    """A simulated sweep of a design (see the module docstring) on the default 8-band sensor.

    Parameters
    ----------
    design : {"mixed", "exposure", "light"}
        See :func:`design_steps`.
    shape : (int, int)
        (H, W) of the simulated frames.
    n_steps : int
        Light steps.
    n_frames : int
        Frames per step.
    darks : bool
        Add a dark step after each light step.
    seed : int
        Seed of the sensor, the design and the noise.
    irradiance : float, optional, W/m^2
        Default: the paper's training level (lamp A).
    **params
        :class:`hsiffc.simulate.SensorParams` fields (default: no dark current, so that the
        base model's constant dark level is right).

    Returns
    -------
    Sweep
        Raw frames (N, H, W) in DN with ``meta["truth"]``.
    """
    params.setdefault("dark_current_dn_per_ms", 0.0)
    sensor = MosaicSensor(shape, seed=seed, params=SensorParams(**params))
    t, levels = design_steps(design, n_steps, seed)
    irr = PAPER_LIGHT_W_M2["training"] if irradiance is None else irradiance
    return sensor.sweep_varying_light(t, levels, "lamp A", irradiance_w_m2=irr,
                                      n_frames=n_frames, darks=darks, seed=seed + 100)


def write_emva1288(sweep: Sweep, folder, *, overwrite: bool = False) -> Path:
    """Write a sweep as an EMVA 1288 measurement: ``EMVA1288_Data.txt`` (exposures in ns,
    photons per pixel per step) and one 8- or 16-bit PNG per frame under ``images/``.

    Light steps need photon counts (``sweep.photons``); a simulated sweep from
    ``sweep_varying_light`` has relative ones.

    Parameters
    ----------
    sweep : Sweep
        Frames with photon counts for the light steps.
    folder : str or Path
        Output folder (created).
    overwrite : bool
        Replace existing files.

    Returns
    -------
    Path
        The descriptor ``EMVA1288_Data.txt``.

    Raises
    ------
    hsiffc.files.atomic.OutputExistsError
        A file to write exists and ``overwrite`` is false.
    ValueError
        A light step has no photon count.
    """
    import cv2

    folder = Path(folder)
    descriptor = folder / "EMVA1288_Data.txt"
    light = sweep.kind == "light"
    if np.any(light & ~np.isfinite(sweep.photons)):
        raise ValueError("every light frame needs a photon count (sweep.photons) to be written "
                         "in EMVA 1288 format")
    dtype = np.uint8 if sweep.bit_depth <= 8 else np.uint16
    h, w = sweep.frame_shape
    lines = ["# simulated by hsiffc (hsiffc.diagnose.simulated.write_emva1288)",
             f"# {sweep.summary()}", "v 3.0", f"n {sweep.bit_depth} {w} {h}"]
    (folder / "images").mkdir(parents=True, exist_ok=True)
    for i, s in enumerate(sweep.steps()):
        sel = np.flatnonzero(sweep.step == s)
        f0 = sel[0]
        exp_ns = sweep.exposure_ms[f0] * 1e6
        lines.append(f"b {exp_ns:.6g} {sweep.photons[f0]:.9g}" if light[f0]
                     else f"d {exp_ns:.6g}")
        for j, f in enumerate(sel):
            name = f"images/{'b' if light[f0] else 'd'}_{i:03d}_snap_{j + 1:03d}.png"
            ok, buf = cv2.imencode(".png", np.ascontiguousarray(sweep.data[f]).astype(dtype))
            if not ok:
                raise OSError(f"{folder / name}: PNG encoding failed")
            with atomic_path(folder / name, overwrite=overwrite) as tmp:
                Path(tmp).write_bytes(buf.tobytes())
            lines.append(f"i {name}")
    atomic_write_text(descriptor, "\n".join(lines) + "\n", overwrite=overwrite)
    return descriptor
