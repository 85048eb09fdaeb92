"""The Release 4.0 figures beyond the classic set, against the EMVA 1288 reference
implementation itself (``emva1288`` from PyPI, the ``emva-reference`` extra) run on the three
shared sets at test time: the row, column and pixel parts of DSNU and PRNU, the defect-pixel
histograms (plain and accumulated: every bin and count), the spectrograms' power arrays, and
the linearity deviation ``LE_mean`` is the mean of. Skipped with the reason when the shared
data or the reference are absent.

The reference is run by :func:`hsiffc.emva1288.agreement.run_reference` (which gives numpy 2
back the one function the reference 1.0.2 still calls, ``np.asfarray``, while it runs).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from hsiffc.emva1288 import characterise
from hsiffc.emva1288.agreement import RELEASE4_FIGURES, compare_release4, run_reference
from hsiffc.io import open_source

SHARED_DATA = Path(os.environ.get("HSIFFC_SHARED_DATA",
                                  Path(__file__).resolve().parents[3] / "shared" / "data"))
SETS = ("emva1288-cmos8-roi", "emva1288-refsim-linear12-exposure",
        "emva1288-refsim-linear10-light")
SPLIT = ("DSNU1288_row", "DSNU1288_col", "DSNU1288_pixel", "PRNU1288_row", "PRNU1288_col",
         "PRNU1288_pixel")


@pytest.fixture(scope="module", params=SETS)
def both(request):
    pytest.importorskip("emva1288", reason="the EMVA 1288 reference implementation is not "
                        "installed (pip install 'hsiffc[emva-reference]')")
    folder = SHARED_DATA / request.param
    if not folder.is_dir():
        pytest.skip(f"{folder} not found: this test needs the shared data (set "
                    "HSIFFC_SHARED_DATA to its folder)")
    with open_source(folder) as src:
        ours = characterise(src)
    return request.param, run_reference(folder), ours


def test_the_agreement_table_holds_the_release4_figures(both):
    name, ref, ours = both
    rows = {r["figure"]: r for r in compare_release4(ours["figures"], ref["figures"])}
    assert set(rows) == set(RELEASE4_FIGURES)
    assert all(r["agrees"] for r in rows.values()), [r for r in rows.values()
                                                      if not r["agrees"]]


def test_row_column_pixel_split_agrees(both):
    name, ref, ours = both
    f = ours["figures"]
    for fig in SPLIT:
        r = ref["figures"][fig]
        mine = f[fig]["value"]
        if np.isnan(r):
            assert mine is None, (name, fig)
        else:
            assert mine == pytest.approx(r, rel=1e-9, abs=1e-12), (name, fig, mine, r)
    # and the DN variants are the e- ones times K
    for part in ("row", "col", "pixel"):
        if f[f"DSNU1288_{part}"]["value"] is not None:
            assert f[f"DSNU1288_{part}_DN"]["value"] == pytest.approx(
                f[f"DSNU1288_{part}"]["value"] * f["K"]["value"], rel=1e-12)


def test_defect_pixel_histograms_agree_bin_for_bin(both):
    name, ref, ours = both
    h = ours["defect_pixels"]
    for key in ("DSNU", "PRNU", "DSNU_accumulated", "PRNU_accumulated"):
        mine, theirs = h[key], ref["histograms"][key]
        assert len(mine["bins"]) == len(theirs["bins"]), (name, key)
        np.testing.assert_allclose(mine["bins"], theirs["bins"], rtol=1e-12, atol=1e-9)
        np.testing.assert_allclose(mine["values"], theirs["values"], rtol=1e-12, atol=0)
        if "model" in mine:
            np.testing.assert_allclose(mine["model"], theirs["model"], rtol=1e-9, atol=1e-9)
    # the standard's counts: every pixel of the (filtered) image is in exactly one bin, and
    # the accumulated histogram starts at 100 % and falls
    n_dark = ours["n_pixels"]
    assert int(np.sum(h["DSNU"]["values"])) == n_dark
    rows, cols = ours["frame_shape"]
    assert int(np.sum(h["PRNU"]["values"])) == (rows - 4) * (cols - 4)
    for key in ("DSNU_accumulated", "PRNU_accumulated"):
        v = np.asarray(h[key]["values"])
        assert v[0] == pytest.approx(100.0) and np.all(np.diff(v) <= 0)


def test_spectrogram_power_agrees(both):
    name, ref, ours = both
    sp = ours["spectrograms"]
    for kind in ("DSNU", "PRNU"):
        for axis in ("horizontal", "vertical"):
            theirs = ref["spectrograms"][kind][axis]
            np.testing.assert_allclose(sp[kind][axis]["power"], theirs, rtol=1e-9,
                                       atol=1e-12 * theirs.max())
    # hsiffc's PRNU amplitude is the standard's percent of the mean signal
    mean = ours["spatial"]["light"]["avg_mean"] - ours["spatial"]["dark"]["avg_mean"]
    np.testing.assert_allclose(sp["PRNU"]["horizontal"]["amplitude"],
                               100 * np.sqrt(ref["spectrograms"]["PRNU"]["horizontal"]) / mean,
                               rtol=1e-9)
    f = sp["PRNU"]["horizontal"]["frequency"]
    assert f[0] == 0 and f[-1] == pytest.approx(0.5, abs=1 / len(f))


def test_le_mean_is_at_most_the_largest_linearity_error(both):
    _, _, ours = both
    f = ours["figures"]
    assert 0 < f["LE_mean"]["value"] <= max(abs(f["LE_min"]["value"]), abs(f["LE_max"]["value"]))
