"""hsiffc's EMVA 1288 figures beside the reference implementation's, on the shared data sets.

``emva1288-reference-figures.json`` (in the shared data folder) holds, per data set, the figures
the standard's reference implementation (``emva1288``, Release 4.0 code) computed with its
documented call sequence. :func:`compare_with_reference` characterises each set that is present
and lists every figure beside the reference with its difference and the tolerance it must meet:
0.5 % relative for K, R, QE, the dark noise, DSNU, PRNU, saturation, SNR, dynamic range and
threshold; 0.05 percentage points for the linearity errors; 2 % relative for the dark currents.
"""

from __future__ import annotations

import json
from pathlib import Path

from ..errors import DataFormatError
from .compute import FIGURES

__all__ = ["REFERENCE_FILE", "TOLERANCES", "RELEASE4_FIGURES", "compare_with_reference",
           "compare_figures", "render_agreement", "run_reference"]

REFERENCE_FILE = "emva1288-reference-figures.json"
#: figure -> (kind, tolerance): "rel" relative, "abs" absolute in the figure's unit
TOLERANCES = {name: ("rel", 0.005) for name in FIGURES}
TOLERANCES.update({"LE_min": ("abs", 0.05), "LE_max": ("abs", 0.05),
                   "u_I_mean": ("rel", 0.02), "u_I_var": ("rel", 0.02)})
#: Release 4.0 figures the reference computes but its figures file does not hold: compared
#: with the installed reference (:func:`run_reference`), to 1e-9 relative
RELEASE4_FIGURES = ("DSNU1288_row", "DSNU1288_col", "DSNU1288_pixel", "PRNU1288_row",
                    "PRNU1288_col", "PRNU1288_pixel", "LE_mean")
RELEASE4_TOLERANCE = 1e-9


def run_reference(folder) -> dict | None:
    """What the installed reference implementation (``emva1288``, the ``emva-reference`` extra)
    computes on the EMVA 1288 set in ``folder`` beyond its figures file, or None when it is not
    installed.

    Returns
    -------
    dict or None
        ``figures`` (the split of DSNU and PRNU under its names, NaN where it gives NaN;
        ``LE_mean``: the mean absolute value of its linearity deviation over its fit range,
        which it does not compute itself), ``histograms`` (its four defect-pixel histograms:
        ``bins``, ``values``, ``model``), ``spectrograms`` (its ``FFT1288`` power arrays of
        the dark and of the (light - dark) mean images, horizontal and vertical).
    """
    import importlib.util
    import logging

    import numpy as np

    if importlib.util.find_spec("emva1288") is None:
        return None
    # the reference (1.0.2) calls np.asfarray, which numpy 2 removed: given back while it runs
    added = not hasattr(np, "asfarray")
    if added:
        np.asfarray = lambda a, dtype=np.float64: np.asarray(a, dtype=dtype)
    try:
        from emva1288.process import (Data1288, LoadImageData, ParseEmvaDescriptorFile,
                                      Results1288)
        from emva1288.process import routines

        quiet = logging.ERROR
        parser = ParseEmvaDescriptorFile(str(Path(folder) / "EMVA1288_Data.txt"), loglevel=quiet)
        data = Data1288(LoadImageData(parser.images, loglevel=quiet).data, loglevel=quiet)
        ref = Results1288(data.data, loglevel=quiet)
        figs = {name: float(getattr(ref, name)) for name in RELEASE4_FIGURES[:-1]}
        lin = ref.linearity()
        dev = lin["relative_deviation"][ref.index_linearity_min:ref.index_linearity_max + 1]
        figs["LE_mean"] = float(np.abs(dev).mean())
        hist = {"DSNU": ref.histogram_DSNU, "PRNU": ref.histogram_PRNU,
                "DSNU_accumulated": ref.histogram_DSNU_accumulated,
                "PRNU_accumulated": ref.histogram_PRNU_accumulated}
        sp = ref.spatial
        diff = (sp["sum"] - sp["sum_dark"]) / sp["L"]
        spec = {"DSNU": {"horizontal": routines.FFT1288(sp["sum_dark"], n=sp["L"]),
                         "vertical": routines.FFT1288(sp["sum_dark"], rotate=True, n=sp["L"])},
                "PRNU": {"horizontal": routines.FFT1288(diff),
                         "vertical": routines.FFT1288(diff, rotate=True)}}
    finally:
        if added:
            del np.asfarray
    return {"figures": figs, "histograms": hist, "spectrograms": spec}


def compare_release4(ours: dict, reference: dict) -> list[dict]:
    """Rows as :func:`compare_figures` for :data:`RELEASE4_FIGURES` against
    :func:`run_reference`'s figures (NaN in the reference: undefined)."""
    import math

    rows = []
    for name in RELEASE4_FIGURES:
        mine = ours.get(name, {}).get("value")
        ref = reference.get(name)
        ref = None if ref is None or math.isnan(ref) else ref
        if mine is None or ref is None:
            diff, ok = None, mine is None and ref is None
        else:
            diff = (mine - ref) / abs(ref) if ref else mine - ref
            ok = abs(diff) <= RELEASE4_TOLERANCE
        rows.append({"figure": name, "unit": ours.get(name, {}).get("unit", ""), "ours": mine,
                     "reference": ref, "difference": diff, "kind": "rel",
                     "tolerance": RELEASE4_TOLERANCE, "agrees": bool(ok)})
    return rows


def compare_figures(ours: dict, reference: dict) -> list[dict]:
    """One row per figure: ours, the reference, the difference and whether it is within the
    tolerance (both undefined counts as agreeing; one undefined does not)."""
    rows = []
    for name in FIGURES:
        mine = ours.get(name, {}).get("value")
        ref = (reference.get(name) or {}).get("value")
        kind, tol = TOLERANCES[name]
        if mine is None or ref is None:
            diff, ok = None, mine is None and ref is None
        else:
            diff = (mine - ref) / abs(ref) if kind == "rel" else mine - ref
            ok = abs(diff) <= tol
        rows.append({"figure": name, "unit": FIGURES[name], "ours": mine, "reference": ref,
                     "difference": diff, "kind": kind, "tolerance": tol, "agrees": bool(ok)})
    sat_ref = (reference.get("index_u_ysat") or {}).get("value")
    if sat_ref is not None:
        rows.append({"figure": "index_u_ysat", "unit": "index",
                     "ours": ours.get("_index_u_ysat"), "reference": sat_ref,
                     "difference": None if ours.get("_index_u_ysat") is None else
                     ours["_index_u_ysat"] - sat_ref, "kind": "abs", "tolerance": 0,
                     "agrees": ours.get("_index_u_ysat") == sat_ref})
    return rows


def compare_with_reference(data_dir, *, reference_file=None, run_release4: bool = True) -> dict:
    """Characterise every shared data set the reference file names and compare.

    Parameters
    ----------
    data_dir : path-like
        The shared data folder (holds the data sets and ``emva1288-reference-figures.json``).
    reference_file : path-like, optional
        Another reference file.
    run_release4 : bool
        Also compare :data:`RELEASE4_FIGURES` with the reference implementation run on each
        set, when it is installed (:func:`run_reference`).

    Returns
    -------
    dict
        ``about`` (how the reference figures were made), ``datasets`` (name -> ``rows`` of
        :func:`compare_figures`, ``all_agree``, or ``missing`` when the set is not there) and
        ``all_agree``.

    Raises
    ------
    DataFormatError
        The reference file is missing or not what it should be.
    """
    from ..io import open_source
    from .compute import characterise

    data_dir = Path(data_dir)
    ref_path = Path(reference_file) if reference_file else data_dir / REFERENCE_FILE
    if not ref_path.is_file():
        raise DataFormatError("reference figures not found; give the shared data folder that "
                              f"holds {REFERENCE_FILE}", path=ref_path)
    try:
        ref = json.loads(ref_path.read_text(encoding="utf-8"))
        sets = ref["datasets"]
    except (ValueError, KeyError) as exc:
        raise DataFormatError(f"not a reference-figures file ({exc}); it needs 'datasets'",
                              path=ref_path) from exc
    out = {"about": ref.get("about", ""), "reference_file": str(ref_path), "datasets": {}}
    for name, figs in sets.items():
        folder = data_dir / name
        if not folder.exists():
            out["datasets"][name] = {"missing": f"{folder} not found"}
            continue
        with open_source(folder) as src:  # streamed, as the command reads it
            res = characterise(src)
        ours = dict(res["figures"])
        ours["_index_u_ysat"] = res["fit_ranges"]["index_u_ysat"]
        rows = compare_figures(ours, figs)
        if run_release4:
            ref4 = run_reference(folder)
            if ref4 is not None:
                rows += compare_release4(ours, ref4["figures"])
                out["release4_reference"] = "the installed reference implementation"
        out["datasets"][name] = {"rows": rows, "all_agree": all(r["agrees"] for r in rows),
                                 "notes": res["notes"]}
    present = [d for d in out["datasets"].values() if "rows" in d]
    out["all_agree"] = bool(present) and all(d["all_agree"] for d in present)
    return out


def _v(v) -> str:
    return "n/a" if v is None else f"{v:.6g}"


def render_agreement(cmp: dict) -> str:
    """The three data sets' figures beside the reference's, as Markdown."""
    names = list(cmp["datasets"])
    lines = ["# EMVA 1288 figures against the reference implementation", "",
             "Reference: `" + Path(cmp["reference_file"]).name + "` (" + cmp["about"] + ")", "",
             "Tolerances: 0.5 % relative for every figure except the linearity errors (0.05 "
             "percentage points) and the dark currents (2 % relative); the saturation index "
             "must be the same. Difference: relative for the former, absolute for the "
             "linearity errors and the index." + (
                 " The Release 4.0 figures the file does not hold (" + ", ".join(
                     f"`{n}`" for n in RELEASE4_FIGURES) + ") are compared with the reference "
                 "implementation run on each set (`emva1288` from PyPI), to "
                 f"{RELEASE4_TOLERANCE:g} relative; its `LE_mean` is the mean absolute value "
                 "of its own linearity deviation over its fit range (it does not report one)."
                 if cmp.get("release4_reference") else ""), "",
             "| figure | unit | " + " | ".join(f"{n}: hsiffc | reference | difference"
                                                 for n in names) + " |",
             "|---|---|" + "---:|---:|---:|" * len(names)]
    rows = {}
    for n in names:
        for r in cmp["datasets"][n].get("rows", []):
            rows.setdefault(r["figure"], {})[n] = r
    for fig, per in rows.items():
        unit = next(iter(per.values()))["unit"]
        cells = []
        for n in names:
            r = per.get(n)
            if r is None:
                cells += ["", "", ""]
                continue
            if r["difference"] is None:
                d = "both undefined" if r["agrees"] else "**one undefined**"
            elif r["kind"] == "rel":
                d = f"{100 * r['difference']:+.2g} %"
            else:
                d = f"{r['difference']:+.2g}"
            if not r["agrees"]:
                d = f"**{d} (outside {r['tolerance']:g})**"
            cells += [_v(r["ours"]), _v(r["reference"]), d]
        lines.append(f"| `{fig}` | {unit} | " + " | ".join(cells) + " |")
    lines.append("")
    for n in names:
        d = cmp["datasets"][n]
        if "missing" in d:
            lines.append(f"- {n}: not compared ({d['missing']})")
        else:
            verdict = "every figure within its tolerance" if d["all_agree"] else \
                "**some figures outside their tolerance**"
            lines.append(f"- {n}: {verdict}" + ("; " + "; ".join(d["notes"]) if d["notes"]
                                                 else ""))
    return "\n".join(lines) + "\n"
