"""Text helpers shared by the reports: CSV tables and number formatting for Markdown."""

from __future__ import annotations

import csv
import io

import numpy as np

__all__ = ["csv_text", "fmt_value"]


def fmt_value(v, nd: int = 2, signed: bool = False) -> str:
    """A number for a Markdown table: ``nd`` decimals, ``"n/a"`` for None, NaN or inf.

    Examples
    --------
    >>> fmt_value(1.2345), fmt_value(None), fmt_value(0.5, 1, signed=True)
    ('1.23', 'n/a', '+0.5')
    """
    if v is None or (isinstance(v, (float, np.floating)) and not np.isfinite(v)):
        return "n/a"
    return f"{v:+.{nd}f}" if signed else f"{v:.{nd}f}"


def csv_text(header, rows) -> str:
    """CSV text with a header line; floats to 6 significant digits, non-finite as empty cells,
    booleans as 0/1.

    Parameters
    ----------
    header : sequence of str
    rows : iterable of sequences
        One sequence of cells per row.

    Examples
    --------
    >>> print(csv_text(["a", "b"], [[1.0, True], [float("nan"), "x"]]), end="")
    a,b
    1,1
    ,x
    """
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(header)
    for r in rows:
        w.writerow([_cell(v) for v in r])
    return buf.getvalue()


def _cell(v):
    if isinstance(v, (bool, np.bool_)):
        return int(v)
    if isinstance(v, (float, np.floating)):
        return "" if not np.isfinite(v) else f"{float(v):.6g}"
    if isinstance(v, np.integer):
        return int(v)
    return v
