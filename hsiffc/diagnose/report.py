"""The diagnosis report: Markdown with residual plots before and after, and the JSON."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..files.atomic import atomic_path, atomic_write_text
from .effects import EFFECTS
from .structure import bin_index


def public(result: dict) -> dict:
    """The JSON-safe part of a :func:`hsiffc.diagnose.diagnose` result.

    Parameters
    ----------
    result : dict
        From :func:`hsiffc.diagnose.diagnose`.

    Returns
    -------
    dict
        Without the ``_``-prefixed (array) entries.
    """
    return {k: v for k, v in result.items() if not k.startswith("_")}


def headline(result) -> list[str]:
    """The first lines of a report (and of the command's output): the verdict, and which
    selected effects are findings and which are stand-ins for what the library lacks.

    Parameters
    ----------
    result : Diagnosis or dict
        From :func:`hsiffc.diagnose.diagnose`.

    Returns
    -------
    list of str
    """
    lines = []
    stand = [e["name"] for e in result["effects"] if e.get("stand_in_for_unexplained")]
    found = [e["name"] for e in result["effects"] if not e.get("stand_in_for_unexplained")]
    if result["unexplained"]:
        lines.append(f"Unexplained: {result['unexplained_reason']}.")
    if stand:
        lines.append(f"Stand-ins, not findings: {', '.join(stand)} (each stands in for "
                     "structure the effect library does not describe; their parameters are "
                     "not a measurement of that effect).")
    lines.append(f"Findings: {', '.join(found) or 'none'}.")
    return lines


def write_json(result: dict, path) -> None:
    """Write the JSON-safe part of a result to ``path`` atomically.

    Parameters
    ----------
    result : dict
        From :func:`hsiffc.diagnose.diagnose`.
    path : str or Path
        Output file.
    """
    atomic_write_text(Path(path), json.dumps(public(result), indent=2, default=float) + "\n")


def binned(x, res, mask, bins):
    """Mean and standard error of ``res`` in bins of ``x`` (quantile bins, or one bin per
    distinct value where the quantiles collapse).

    Parameters
    ----------
    x : ndarray, broadcastable to ``res``
        What to bin by (e.g. signal in DN).
    res : ndarray, (P, S), DN
        Residuals.
    mask : ndarray of bool, (P, S)
        Samples to use.
    bins : int
        Number of bins at most.

    Returns
    -------
    centres, means, standard_errors : ndarray, (n_bins,)
        Bin centres in the unit of ``x``; mean residual and its standard error in DN.
    """
    x = np.broadcast_to(x, res.shape)
    idx = bin_index(x, mask, bins)[mask]
    xv, rv = x[mask], res[mask]
    if xv.size == 0:
        return np.array([]), np.array([]), np.array([])
    n = np.bincount(idx)
    keep = n > 0
    mean = np.bincount(idx, weights=rv)[keep] / n[keep]
    centre = np.bincount(idx, weights=xv)[keep] / n[keep]
    var = np.bincount(idx, weights=rv * rv)[keep] / n[keep] - mean ** 2
    return centre, mean, np.sqrt(np.maximum(var, 0) / n[keep])


def _plot(result: dict, path: Path) -> None:
    from matplotlib.figure import Figure  # no pyplot: no backend state is touched

    a = result["_arrays"]
    valid, light = a["valid"], a["light"]
    lmask = valid & light[None, :]
    dmask = valid & ~light[None, :]
    shape = valid.shape
    panels = [
        ("signal above dark (DN)", a["signal"], lmask, 30),
        ("exposure (ms), light steps", np.broadcast_to(a["t"], shape), lmask, 20),
        ("acquisition order (-1 .. 1)", np.broadcast_to(a["order"], shape), valid, 20),
        ("exposure (ms), dark steps", np.broadcast_to(a["t"], shape), dmask, 15),
        ("row", np.broadcast_to(a["rows"][:, None], shape), valid, 16),
        ("column", np.broadcast_to(a["cols"][:, None], shape), valid, 16),
    ]
    fig = Figure(figsize=(12, 6.5), dpi=90)
    axes = fig.subplots(2, 3)
    for ax, (label, x, mask, bins) in zip(axes.ravel(), panels):
        for key, colour, name in (("res_before", "tab:orange", "base model"),
                                  ("res_after", "tab:blue", "with selected effects")):
            c, m, se = binned(x, a[key], mask, bins)
            ax.errorbar(c, m, yerr=se, fmt="o-", ms=3, lw=1, color=colour, label=name)
        ax.axhline(0, color="k", lw=0.6)
        ax.set_xlabel(label)
        ax.set_ylabel("held-out data - model (DN)")
    axes[0, 0].legend(fontsize=8)
    fig.suptitle(f"Held-out residual, binned (mean +- standard error); noise floor "
                 f"{result['noise_floor_dn']:.3g} DN", fontsize=10)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")


def write_report(result: dict, outdir) -> Path:
    """Write ``report.md``, ``residuals.png`` and ``diagnosis.json`` into ``outdir``.

    Parameters
    ----------
    result : dict
        From :func:`hsiffc.diagnose.diagnose`.
    outdir : str or Path
        Output folder (created).

    Returns
    -------
    Path
        The report (``report.md``).
    """
    outdir = Path(outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    _plot(result, outdir / "residuals.png")
    write_json(result, outdir / "diagnosis.json")
    b, af = result["before"], result["after"]
    lines = [f"# hsiffc diagnosis of {result['dataset']}", ""]
    lines += [f"{line}" for line in headline(result)] + [""]
    lines += [f"Base model: {result['base_model']}.", "",
             f"{result['n_pixels']} pixels analysed (of {result['n_pixels_sensor']}), "
             f"{result['n_samples']} valid held-out samples, {result['n_invalid_samples']} "
             f"left out (clipped, near full scale or unusable). Held out: {result['held_out']}.",
             "", "| | RMS (DN) | systematic RMS (DN) |", "|---|---|---|",
             f"| temporal noise floor | {result['noise_floor_dn']:.4g} | |",
             f"| base model | {b['rms_dn']:.4g} | {b['systematic_rms_dn']:.4g} |",
             f"| with the selected effects | {af['rms_dn']:.4g} | {af['systematic_rms_dn']:.4g} |",
             "", f"Selection rule: {result['selection_rule']}.", "",
             f"Noise measured from: {result['noise_source']}.", "",
             f"Dark model: {result['dark_model']['model']} ({result['dark_model']['reason']}).",
             "", f"Leakage: **{result['leakage']['verdict']}** ({result['leakage']['reason']}).",
             ""]
    if result["design"]["notes"]:
        lines += [f"Design note: {n}." for n in result["design"]["notes"]] + [""]
    if result["effects"]:
        lines += ["## Selected effects", ""]
        for e in result["effects"]:
            params = ", ".join(f"{k} = {v:.4g}" if isinstance(v, float) else f"{k} = {v}"
                               for k, v in e["params"].items())
            stand = (f" Stand-in, not a finding: {e['stand_in_reason']}."
                     if e.get("stand_in_for_unexplained") else "")
            lines += [f"- `{e['name']}` ({params}): {e['interpretation']}.{stand}"]
    else:
        lines += ["No candidate effect beats the base model by more than the noise allows.", ""]
    if result["skipped"]:
        lines += ["", "## Candidates this design cannot identify (skipped)", ""]
        lines += [f"- `{s['name']}`: {s['reason']}." for s in result["skipped"]]
    lines += ["", "## Candidates", "",
              "| base | round | effect | held-out RMS (DN) | gain in MSE (DN^2) | standard error | "
              "BIC | selected |", "|---|---|---|---|---|---|---|---|"]
    for c in result["candidates"]:
        lines.append(f"| {c['base']} | {c['round']} | {c['name']} | {c['heldout_rms_dn']:.4g} | "
                     f"{c['heldout_mse_gain_dn2']:.3g} | {c['gain_standard_error_dn2']:.2g} | "
                     f"{c['criterion']:.6g} | {'yes' if c.get('selected_in_round') else ''}"
                     f"{' (rejected: ' + c['rejected'] + ')' if c.get('rejected') else ''} |")
    lines += ["", "## Structure left in the held-out residual", "",
              "| grouping | bins | chi2 | p | structured RMS (DN) | expected from noise (DN) | "
              "significant |", "|---|---|---|---|---|---|---|"]
    for f in result["residual_structure_after"]:
        null = f.get("null_structured_rms_dn")
        lines.append(f"| {f['grouping']} | {f['bins']} | {f['chi2']:.1f} | {f['p_value']:.2g} | "
                     f"{f['structured_rms_dn']:.3g} | {'' if null is None else f'{null:.3g}'} | "
                     f"{'yes' if f['significant'] else ''} |")
    reason = result.get("unexplained_reason", "")
    verdict = (f"**Unexplained**: {reason}. It is reported, not forced onto the nearest "
               "candidate (see the table and the figure)."
               if result["unexplained"] else
               f"Nothing unexplained: {reason}.")
    lines += ["", verdict, ""]
    if result.get("ambiguous"):
        lines += ["## Equally good explanations", ""]
        lines += [f"- {' / '.join(a['effects'])}: {a['reason']}." for a in result["ambiguous"]]
        lines += [""]
    lines += ["![residuals](residuals.png)", "",
              "## The effect library", ""]
    lines += [f"- `{e.name}` ({e.scope}): {e.summary}" for e in EFFECTS.values()]
    path = outdir / "report.md"
    atomic_write_text(path, "\n".join(lines) + "\n")
    return path
