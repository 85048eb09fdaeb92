"""Commands on sweeps: ``info``, ``simulate``, ``select``."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from ..errors import HsiffcError, ParameterError
from .args import count, exposure_ms, percent, positive, real, seed
from .common import add_input_options, add_overwrite, input_overrides, write_json


def register(sub) -> None:
    """Add this module's sub-commands to the parser's sub-parsers.

    Parameters
    ----------
    sub : argparse._SubParsersAction
        What ``ArgumentParser.add_subparsers()`` returned (see :func:`hsiffc.cli.build_parser`).
    """
    _add_info(sub)
    _add_simulate(sub)
    _add_select(sub)


def _add_info(sub):
    p = sub.add_parser("info", help="describe frames of any supported format and where each "
                                    "metadata field came from (of hsiffc correct's outputs and "
                                    "the ENVI, OME-TIFF and netCDF cubes hsiffc writes: bands, "
                                    "DQ counts, provenance)")
    p.add_argument("sweep", type=Path, nargs="+", help="files, folders or globs")
    p.add_argument("--json", type=Path, default=None, help="also write the description as JSON")
    add_input_options(p)
    add_overwrite(p)
    p.set_defaults(func=_cmd_info, input_args=("sweep",), output_args=("json",))


def _cmd_info(args) -> int:
    from ..io import open_source
    from ..io.corrected import is_corrected_file

    kinds = [_written_kind(Path(p), is_corrected_file) for p in args.sweep]
    if all(kinds):  # outputs of hsiffc correct and cubes: what each holds, its provenance
        docs = [_info_cube(Path(p), kind) if kind != "corrected" else _info_corrected(p)
                for p, kind in zip(args.sweep, kinds)]
        if args.json:
            write_json(args.json, docs if len(docs) > 1 else docs[0])
        return 0
    with open_source(args.sweep, overrides=input_overrides(args), inspect=True) as src:
        print(src.describe())
        steps = _stream_steps(src)
    missing = sorted(set(src.missing))
    print(f"{'step':>5} {'kind':>5} {'exposure_ms':>12} {'photons':>10} {'frames':>6} "
          f"{'mean_dn':>9} {'max_dn':>7}")
    for s in steps:
        print(f"{s['step']:>5} {s['kind']:>5} {s['exposure_ms']:>12.6g} "
              f"{np.nan if s['photons'] is None else s['photons']:>10.4g} {s['n_frames']:>6} "
              f"{s['mean_dn']:>9.2f} {s['max_dn']:>7.0f}")
    if args.json:
        doc = {"source": src.label, "files": [str(f) for f in src.files], "format": src.format,
               "n_frames": src.n_frames, "frame_shape": list(src.frame_shape),
               "dtype": str(src.dtype), "bit_depth": src.bit_depth,
               "mosaic": None if src.mosaic is None else src.mosaic.to_dict(),
               "origins": src.origins, "notes": src.notes, "missing": missing, "steps": steps}
        write_json(args.json, doc)
    if missing:
        print(f"missing: {', '.join(missing)} (the other commands refuse these files until it "
              "is given; see above how)")
    return 0


def _written_kind(path: Path, is_corrected_file) -> str | None:
    """``"corrected"`` for an output of ``hsiffc correct`` (or an hsiffc TIFF cube), the cube
    format (``"envi"``, ``"ome"``, ``"netcdf"``) for a cube file :func:`hsiffc.cubes.read_cube`
    reads (an ENVI header with one wavelength per band, the OME-TIFF and netCDF cubes hsiffc
    writes), None for anything else (raw frames: :func:`hsiffc.io.open_source` describes
    them, or says why it cannot)."""
    if not path.is_file():
        return None
    name = path.name.lower()
    try:
        if name.endswith(".nc"):
            return "netcdf"
        if name.endswith((".ome.tif", ".ome.tiff")):
            import tifffile

            with tifffile.TiffFile(path) as tf:
                if tf.is_ome and "hsiffc-cube" in (tf.ome_metadata or ""):
                    return "ome"
        if name.endswith((".hdr", ".img")):
            from ..io.envi import parse_envi_header

            head = parse_envi_header(path.with_suffix(".hdr"))
            wl, bands = head.get("wavelength"), str(head.get("bands", "1")).strip()
            if "hsiffc version" in head or "dq file" in head or (
                    isinstance(wl, list) and bands.isdigit() and len(wl) == int(bands) > 1):
                return "envi"
            return None
    except Exception:  # unreadable here: the frame reader says why
        return None
    if not is_corrected_file(path):
        return None
    from ..io.corrected import read_provenance

    prov = read_provenance(path)  # write_cube's own TIFF keeps the cube's history and attrs
    return "tiff" if isinstance(prov.get("attrs"), dict) and "history" in prov else "corrected"


def _info_cube(path: Path, fmt: str) -> dict:
    """``hsiffc info`` on a cube file: its shape and unit, the bands with their wavelengths,
    the DQ values flagged per bit, and its provenance (history and attributes)."""
    import textwrap

    from ..cubes import read_cube
    from ..data.dq import table

    cube = read_cube(path)
    h, w, b = cube.data.shape
    wl = cube.wavelengths_nm
    positions = cube.positions or [None] * b
    names = cube.band_names()
    bands = [{"band": k, "label": names[k], "wavelength_nm": None if wl is None else wl[k],
              "fwhm_nm": None if cube.fwhm_nm is None else cube.fwhm_nm[k],
              "band_index": cube.band_index[k],
              "position": None if positions[k] is None else list(positions[k])}
             for k in range(b)]
    counts = {r["name"]: int(np.count_nonzero(cube.dq & np.uint32(r["value"])))
              for r in table()}
    flagged = int(np.count_nonzero(cube.dq))
    label = {"envi": "ENVI", "ome": "OME-TIFF", "netcdf": "netCDF", "tiff": "hsiffc TIFF"}[fmt]
    print(f"{path}: {label} cube, {h} x {w} px, {b} bands, float32 {cube.unit}; planes data, "
          f"dq{', alpha' if cube.alpha is not None else ''}")
    print(textwrap.fill("bands: " + ", ".join(names), width=100,
                        initial_indent="  ", subsequent_indent="    "))
    hits = ", ".join(f"{name} {n}" for name, n in counts.items() if n)
    print(f"  DQ: {flagged} of {cube.dq.size} values flagged ({100 * flagged / cube.dq.size:.2f}"
          f" %){': ' + hits if hits else ''}")
    steps = [str(s.get("name", "?")) for s in cube.history if isinstance(s, dict)]
    print(f"  provenance: pipeline {' -> '.join(steps) or 'not recorded'}; "
          + (", ".join(f"{k} {v}" for k, v in cube.attrs.items()
                       if isinstance(v, (str, int, float)))[:400] or "no attributes"))
    return {"path": str(path), "format": fmt, "shape": [h, w, b], "unit": cube.unit,
            "alpha": cube.alpha is not None, "bands": bands, "dq_counts": counts,
            "flagged_values": flagged, "history": list(cube.history), "attrs": cube.attrs}


def _info_corrected(path) -> dict:
    """``hsiffc info`` on an output of ``hsiffc correct``: what it holds and where it came
    from (its provenance; the planes are not read)."""
    from ..io.corrected import read_provenance

    prov = read_provenance(path)
    doc = {"path": str(path), **prov}
    shape = " x ".join(str(s) for s in prov.get("frame_shape", []))
    cube = prov.get("cube") or {}
    what = "cubes" if cube or len(prov.get("frame_shape", [])) == 3 else "frames"
    exposures = sorted({float(e) for e in prov.get("exposure", [])})
    flagged = (prov.get("frames") or {}).get("flagged_fraction") or []
    cal = prov.get("calibration") or {}
    steps = [s.get("name", "?") for s in (prov.get("pipeline") or {}).get("steps", [])]
    src = (prov.get("input") or {}).get("path", "?")
    print(f"{path}: output of hsiffc correct ({prov.get('format')} version "
          f"{prov.get('format_version')}, {prov.get('status')}), written by hsiffc "
          f"{prov.get('hsiffc_version', '?')}")
    print(f"  {prov.get('n_frames')} {what} of {shape} px, planes "
          f"{', '.join(prov.get('planes', []))}; {prov.get('bit_depth')}-bit input "
          f"{prov.get('input_dtype', '')} from {src}")
    print(f"  exposures {', '.join(f'{e:g}' for e in exposures)} "
          f"{prov.get('exposure_unit', 'ms')}; flagged "
          + (f"{100 * float(np.mean(flagged)):.2f} % of pixels on average" if flagged
             else "fraction not recorded"))
    print(f"  pipeline {' -> '.join(steps) or '?'}; calibration "
          f"{cal.get('identity', 'none')}"
          + (f" ({cal.get('method')}, fitted on {cal.get('fitted_on')})" if cal else ""))
    return doc


def _stream_steps(src) -> list:
    """Per acquisition step: kind, exposure, photons, frame count, mean and max DN (streamed:
    one frame in memory at a time). Without step ids, consecutive frames with equal settings
    form a step."""
    steps: list = []
    key_prev, step_id = None, -1
    for raw, m in src:
        key = (None if np.isnan(m.exposure_ms) else m.exposure_ms, m.kind, m.illumination)
        if m.step is not None:
            new, step_id = m.step != step_id, m.step
        else:
            new = key != key_prev
            step_id += int(new)
        key_prev = key
        if new or not steps:
            steps.append({"step": int(step_id), "kind": m.kind, "exposure_ms": m.exposure_ms,
                          "photons": None if np.isnan(m.photons) else m.photons,
                          "n_frames": 0, "mean_dn": 0.0, "max_dn": -np.inf})
        s = steps[-1]
        s["n_frames"] += 1
        s["mean_dn"] += (float(raw.mean(dtype=np.float64)) - s["mean_dn"]) / s["n_frames"]
        s["max_dn"] = max(s["max_dn"], float(raw.max()))
    return steps


def _add_simulate(sub):
    p = sub.add_parser(
        "simulate", help="simulate an exposure sweep of a mosaic sensor and write it as TIFF",
        description="Simulate raw frames of the default (paper) sensor or a square IMEC-like "
                    "mosaic under a named lamp and write an hsiffc TIFF sweep.")
    p.add_argument("output", type=Path, help="TIFF file to write (not overwritten without --overwrite)")
    p.add_argument("--exposures-ms", type=exposure_ms, nargs="+", required=True,
                   help="exposure times in ms")
    p.add_argument("--lamp", default="lamp A",
                   help="'lamp A' (2900 K), 'lamp B' (2200 K), '<T>K', or a CIE illuminant name")
    p.add_argument("--irradiance-w-m2", type=positive, default=None,
                   help="irradiance over 400-1000 nm in W/m^2 (default: the paper's training level)")
    p.add_argument("--frames", type=count, default=2, help="frames per exposure (default 2)")
    p.add_argument("--no-darks", action="store_true", help="do not add dark frames")
    p.add_argument("--shape", type=count, nargs=2, default=(64, 64), metavar=("H", "W"))
    p.add_argument("--mosaic", default="paper8", help="paper8, 4x4 or 5x5")
    p.add_argument("--vignetting", type=_vignetting, default=0.0,
                   help="fraction of the light lost at the corners, 0 <= v < 1 (default 0)")
    p.add_argument("--seed", type=seed, default=0, help="random seed, a whole number >= 0")
    add_overwrite(p)
    p.set_defaults(func=_cmd_simulate, output_args=("output",))


def _vignetting(text: str) -> float:
    """Relative light fall-off at the corners: a finite number 0 <= v < 1."""
    value = real(text)
    if not 0.0 <= value < 1.0:
        raise argparse.ArgumentTypeError(
            f"expected the fraction of light lost at the corners, 0 <= v < 1, got {text!r}")
    return value


def _simulated_lamp(sensor, spec: str, irradiance_w_m2: float, vignetting: float):
    """The lamp ``--lamp`` names on the sensor's wavelength grid, or a one-line ParameterError.

    A colour temperature too low to emit on the sensor's grid (e.g. '1K') overflows Planck's
    law on the way to "no power"; that overflow is expected and not reported as a warning.
    """
    try:
        with np.errstate(over="ignore", under="ignore"):
            illum = sensor.illumination(spec, irradiance_w_m2, vignetting=vignetting)
    except ValueError as exc:
        raise ParameterError(f"--lamp {spec!r} cannot be simulated: {exc}; give e.g. "
                             "--lamp 'lamp A', --lamp 2900K or --lamp D65") from None
    with np.errstate(over="ignore", invalid="ignore"):
        rate = sensor.light_rate(illum)
    if not np.all(np.isfinite(rate)):
        raise ParameterError(f"--irradiance-w-m2 {irradiance_w_m2:g} is too large: the light "
                             "rate of some pixels overflows; give a smaller irradiance")
    return illum


def _check_simulated_size(args) -> None:
    """Refuse a sweep larger than the read limits allow (hsiffc.files.limits: one frame's pixels,
    and the bytes held at once, about 8 per pixel while simulating) before allocating it."""
    from ..files.limits import default_limits

    h, w = args.shape
    limits = default_limits()
    frames = len(args.exposures_ms) * args.frames * (1 if args.no_darks else 2)
    nbytes = frames * h * w * 8
    if h * w > limits.max_frame_pixels or nbytes > limits.max_bytes:
        raise ParameterError(
            f"--shape {h} {w}: {frames} frames of {h * w:,} pixels (about "
            f"{nbytes / 1024 ** 3:.3g} GiB in memory) exceed the limits of "
            f"{limits.max_frame_pixels:,} pixels per frame (HSIFFC_MAX_FRAME_PIXELS) and "
            f"{limits.max_bytes / 1024 ** 3:.3g} GiB (HSIFFC_MAX_BYTES); give a smaller --shape "
            "or fewer frames, or raise the limits")


def _cmd_simulate(args) -> int:
    from ..io import write_sweep
    from ..data.mosaic import Mosaic
    from ..simulate import PAPER_LIGHT_W_M2, MosaicSensor
    from ..spectral import imec_4x4_visible, imec_5x5_nir

    _check_simulated_size(args)
    irr = args.irradiance_w_m2 if args.irradiance_w_m2 is not None else PAPER_LIGHT_W_M2["training"]
    if args.mosaic == "paper8":
        sensor = MosaicSensor(tuple(args.shape), seed=args.seed)
    elif args.mosaic in ("4x4", "5x5"):
        bands = imec_4x4_visible() if args.mosaic == "4x4" else imec_5x5_nir()
        n = 4 if args.mosaic == "4x4" else 5
        sensor = MosaicSensor(tuple(args.shape), seed=args.seed, bands=bands,
                              mosaic=Mosaic.square(n, wavelengths_nm=bands.centres_nm))
    else:
        raise HsiffcError(f"--mosaic must be paper8, 4x4 or 5x5, got {args.mosaic!r}")
    illum = _simulated_lamp(sensor, args.lamp, irr, args.vignetting)
    sweep = sensor.sweep(args.exposures_ms, illum, irradiance_w_m2=irr, n_frames=args.frames,
                         darks=not args.no_darks)
    meta = {k: v for k, v in sweep.meta.items() if k != "truth"}
    meta["irradiance_w_m2"] = irr
    from dataclasses import replace
    write_sweep(args.output, replace(sweep, meta=meta), overwrite=args.overwrite)
    print(f"wrote {args.output}: {sweep.summary()}")
    return 0


def _add_select(sub):
    p = sub.add_parser(
        "select", help="select the training exposure per band by the leakage percentage",
        description="For each band, the longest candidate exposure whose leakage percentage "
                    "alpha stays under the threshold (the paper's section IV.2), with a table of "
                    "alpha per band and exposure like the paper's Table I.")
    p.add_argument("sweep", type=Path, nargs="+",
                   help="candidate training frames (one step per exposure)")
    add_input_options(p)
    p.add_argument("--calibration", type=Path, required=True, help="calibration file (.npz)")
    p.add_argument("--threshold", type=percent, required=True, help="alpha threshold in percent")
    p.add_argument("--alpha", choices=("paper", "model"), default="paper",
                   help="alpha as the paper computes it (k ~ signal/exposure) or with k from the "
                        "model (default: paper)")
    p.add_argument("--statistic", choices=("median", "mean", "p95"), default="median",
                   help="how a band's pixels are summarised (default: median)")
    p.add_argument("--json", type=Path, default=None, help="also write the table as JSON")
    add_overwrite(p)
    p.set_defaults(func=_cmd_select, input_args=("sweep", "calibration"), output_args=("json",))


def _cmd_select(args) -> int:
    from ..calibrate import Calibration
    from ..data.mosaic import mosaic_band_labels, wavelength_order
    from ..io import read_sweep
    from ..leakage.validity import alpha_table

    sweep = read_sweep(args.sweep, overrides=input_overrides(args))
    cal = Calibration.load(args.calibration)
    table = alpha_table(sweep, cal, method=args.alpha, statistic=args.statistic)
    table = table.select(args.threshold)
    print(table.to_text())
    labels = mosaic_band_labels(sweep.mosaic, len(table.selected_ms))
    wl = None if sweep.mosaic is None else sweep.mosaic.wavelengths_nm
    for i in wavelength_order(len(labels), wl):
        e = table.selected_ms[i]
        print(f"{labels[i]}: train at {'none' if np.isnan(e) else f'{e:g} ms'}")
    if args.json:
        write_json(args.json, {"sweep": str(args.sweep), "calibration": str(args.calibration),
                                "calibration_identity": cal.identity, **table.to_dict()})
    return 0

