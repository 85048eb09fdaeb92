"""Data-quality bit flags, one uint32 plane per frame.

Flag, never delete: a flagged pixel keeps a finite value and gains a bit here.

The bit values are hsiffc's own (bits 0 and 1 happen to match JWST's ``DO_NOT_USE`` and
``SATURATED``; the others do not follow JWST's table). Every file hsiffc writes carries the
table (:func:`table`: name, value, meaning), so a DQ plane can be decoded without hsiffc; in
Python, :func:`mask` turns names into a boolean mask::

    >>> dq = np.array([0, 2, 4, 6], DQ_DTYPE)
    >>> mask(dq, "SATURATED|LEAKAGE").tolist()
    [False, True, True, True]
"""

from __future__ import annotations

import enum

import numpy as np

DQ_DTYPE = np.uint32


class DQ(enum.IntFlag):
    """Named data-quality bits: one uint32 plane per frame, one bit per reason.

    A flagged pixel keeps its value and gains a bit; ``GOOD`` (0) is no bit set. Bits combine
    with ``|`` and are tested with ``&``; :func:`mask` selects pixels by bit names, and
    :data:`MEANINGS` and :func:`table` say what each bit means (every file hsiffc writes carries
    that table).

    Examples
    --------
    >>> import numpy as np
    >>> from hsiffc import DQ
    >>> from hsiffc.data.dq import describe, mask
    >>> dq = np.zeros((2, 3), np.uint32)            # every pixel GOOD
    >>> dq[0, 1] |= DQ.SATURATED | DQ.DO_NOT_USE
    >>> int(dq[0, 1]), bool(dq[0, 1] & DQ.SATURATED), bool(dq[0, 1] & DQ.LEAKAGE)
    (3, True, False)
    >>> describe(int(dq[0, 1]))
    ['DO_NOT_USE', 'SATURATED']
    >>> int(mask(dq, "SATURATED").sum())            # pixels with that bit
    1
    """

    GOOD = 0
    DO_NOT_USE = 1 << 0
    SATURATED = 1 << 1  # at full scale (ADC clip) or full well
    LEAKAGE = 1 << 2  # leakage percentage alpha over threshold
    DEAD = 1 << 3
    HOT = 1 << 4
    NO_FLAT = 1 << 5
    NONFINITE = 1 << 6  # input was NaN or inf
    BELOW_DARK = 1 << 7  # response below what zero light can give
    UNREACHABLE = 1 << 8  # no light rate explains the response
    NOT_CONVERGED = 1 << 9
    LEAK_UNCONSTRAINED = 1 << 10  # calibration: the data do not pin the leakage a, b
    OUT_OF_DOMAIN = 1 << 11  # outside the calibration's validity domain
    UNCERTAIN = 1 << 12  # model FFC: the calibration's own errors predict a large pattern


def empty_dq(shape) -> np.ndarray:
    """A DQ plane of the given shape with every pixel GOOD."""
    return np.zeros(shape, dtype=DQ_DTYPE)


def as_dq(plane, name: str = "dq") -> np.ndarray:
    """``plane`` as a uint32 DQ array (no copy when it is one), refusing what is not a set of
    bits: floats (0.5 would become 0), negative integers (-1 would become every bit), complex.

    Examples
    --------
    >>> as_dq(np.array([0, 6], np.int16)).tolist()
    [0, 6]
    """
    a = np.asarray(plane)
    if a.dtype == DQ_DTYPE:
        return a
    if a.dtype.kind not in "biu":
        raise ValueError(f"{name} must hold integer DQ bits (uint32), got dtype {a.dtype}; "
                         f"build it with hsiffc.data.dq.empty_dq or from DQ flags")
    if a.dtype.kind == "i" and a.size and a.min() < 0:
        raise ValueError(f"{name} holds negative values (min {a.min()}); DQ bits are unsigned: "
                         "build it with hsiffc.data.dq.empty_dq or from DQ flags")
    if a.size and a.dtype.itemsize > 4 and a.max() > np.iinfo(DQ_DTYPE).max:
        raise ValueError(f"{name} holds values beyond 32 bits (max {a.max()}); DQ planes are "
                         "uint32")
    return a.astype(DQ_DTYPE)


def describe(value: int) -> list[str]:
    """Names of the bits set in ``value``.

    Examples
    --------
    >>> describe(DQ.SATURATED | DQ.LEAKAGE)
    ['SATURATED', 'LEAKAGE']
    """
    return [f.name for f in DQ if f and (int(value) & int(f)) == int(f)]


#: What each bit means, as written into every output file's DQ table.
MEANINGS = {
    "DO_NOT_USE": "do not use this value: no trustworthy estimate",
    "SATURATED": "at full scale (ADC clip) or full well",
    "LEAKAGE": "leakage percentage alpha above the threshold",
    "DEAD": "dead pixel (no response)",
    "HOT": "hot pixel (dark signal far above its band's)",
    "NO_FLAT": "no valid flat-field value for this pixel",
    "NONFINITE": "the input or the correction was NaN or inf (value set to 0)",
    "BELOW_DARK": "response below what zero light can give",
    "UNREACHABLE": "no light rate explains the response",
    "NOT_CONVERGED": "the per-pixel inversion did not converge",
    "LEAK_UNCONSTRAINED": "calibration: the data do not pin the leakage parameters a and b",
    "OUT_OF_DOMAIN": "outside the calibration's validity domain (exposure or light or bit depth)",
    "UNCERTAIN": "model FFC: the calibration's own errors (factor, dark) predict a fixed-pattern "
                 "error above the stage's uncertain_above_percent of the corrected signal",
}

#: Version of the bit table; raised whenever a bit's value or meaning changes.
TABLE_VERSION = 1


def table() -> list[dict]:
    """The DQ bit table: one ``{"name", "value", "bit", "meaning"}`` per bit, by value.

    Written into every file hsiffc writes (TIFF provenance ``"dq_bits"``, ENVI header
    ``dq bit names`` / ``dq bit values``, netCDF attributes ``flag_masks`` / ``flag_meanings``),
    so a DQ plane is decoded with the file alone.

    Examples
    --------
    >>> table()[1]["name"], table()[1]["value"], table()[1]["bit"]
    ('SATURATED', 2, 1)
    """
    return [{"name": f.name, "value": int(f), "bit": int(f).bit_length() - 1,
             "meaning": MEANINGS[f.name]} for f in DQ if f]


def bits(flags) -> int:
    """The integer value of ``flags``: a DQ, an int, a name or names joined by ``|``, ``+`` or
    ``,`` (``"SATURATED|LEAKAGE"``), or a sequence of those (astropy.nddata.bitmask's
    conventions). Unknown names raise ValueError listing the known ones.

    Examples
    --------
    >>> bits("SATURATED | leakage"), bits(["DEAD", 16]), bits(None)
    (6, 24, 0)
    """
    if flags is None:
        return 0
    top = int(np.iinfo(DQ_DTYPE).max)
    if isinstance(flags, (bool, np.bool_)):
        raise TypeError(f"DQ flags {flags!r} are a bool, not bits; give names "
                        "(\"SATURATED|DEAD\") or an integer 0..4294967295")
    if isinstance(flags, (int, np.integer)):  # DQ members are ints
        if int(flags) < 0 or int(flags) > top:
            raise ValueError(f"DQ flags {flags} are not a 32-bit set of bits (0..{top})")
        return int(flags)
    if isinstance(flags, (bytes, bytearray, memoryview)):
        raise TypeError(f"DQ flags {bytes(flags)[:40]!r} are bytes; give a str (decode it: "
                        "flags.decode()), an integer or a list of names")
    if isinstance(flags, str):
        parts = [p.strip() for p in flags.replace("+", "|").replace(",", "|").split("|")]
        if not any(parts):
            raise ValueError(f"DQ flags {flags[:40]!r} name no flag; give names "
                             "(\"SATURATED|DEAD\"), an integer, or None for all bits")
        value = 0
        for name in filter(None, parts):
            if name.isascii() and name.isdigit():
                value |= bits(int(name) if len(name) <= 10 else top + 1)
                continue
            try:
                value |= int(DQ[name.upper()])
            except KeyError:
                known = ", ".join(f.name for f in DQ if f)
                raise ValueError(f"unknown DQ flag {name[:40]!r}; known flags: {known}") from None
        return value
    try:
        items = iter(flags)
    except TypeError:
        raise TypeError(f"DQ flags of type {type(flags).__name__} are not names, an integer "
                        "or a sequence of those") from None
    value = 0
    for item in items:
        value |= bits(item)
    return value


def mask(dq, flags=None, *, good: bool = False) -> np.ndarray:
    """Boolean mask of the values that carry any of ``flags`` (all bits when None).

    Parameters
    ----------
    dq : array_like of unsigned integers
        A DQ plane or cube.
    flags : str, int, DQ or sequence, optional
        Bits to test, by name (``"SATURATED|LEAKAGE"``), value or both (see :func:`bits`).
    good : bool
        Return the opposite: True where none of ``flags`` is set (the values to keep).

    Returns
    -------
    ndarray of bool, dq's shape

    Examples
    --------
    >>> dq = np.array([0, DQ.SATURATED, DQ.DEAD], DQ_DTYPE)
    >>> mask(dq, "SATURATED|DEAD").tolist(), mask(dq, good=True).tolist()
    ([False, True, True], [True, False, False])
    """
    value = bits(flags) if flags is not None else int(np.iinfo(DQ_DTYPE).max)
    hit = (as_dq(dq) & DQ_DTYPE(value)) != 0
    return ~hit if good else hit
