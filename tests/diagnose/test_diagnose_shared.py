"""Diagnose on the shared data sets nobody here tuned on, one row each on the diagnose page:
every sweep of ``../shared/data`` has its row, and the independent generator's sets (physics
the leakage model leaves out, no leakage) get verdicts that agree with what was put in or say
that the library lacks it. (The reference simulator's linear sets:
``test_diagnose_evaluation.py::test_linear_reference_simulations_stay_linear``.)"""

from __future__ import annotations

import pytest

from hsiffc.diagnose import diagnose
from hsiffc.diagnose import evaluation as ev
from hsiffc.io import read_sweep


def test_every_shared_sweep_is_a_row_of_its_own(shared_set):
    """A sweep added to ../shared/data without a row on the diagnose page fails here."""
    root = shared_set("emva1288-cmos8-roi").parent
    sweeps = sorted(p.name for p in root.iterdir() if (p / "EMVA1288_Data.txt").is_file())
    assert sorted(ev.SHARED_SETS) == sweeps
    assert set(ev.NO_LEAKAGE_SETS) >= set(ev.LINEAR_SETS)
    assert all(ev.SHARED_PUT_IN[name] for name in ev.SHARED_SETS)


def test_a_readout_compression_common_to_every_pixel_is_named(shared_set):
    """indep-cmos10-light-nonlinear: a cubic readout compression (3 % low at full scale) on a
    sensor without leakage, a light sweep at one exposure. The compression is named alone, at
    about its size, and leakage is not needed."""
    out = diagnose(read_sweep(shared_set("indep-cmos10-light-nonlinear")))
    assert out["selected_effects"] == ["readout_nonlinearity"], out["candidates"]
    assert out["leakage"]["verdict"] == "not needed"
    assert not out["unexplained"] and out["stand_ins"] == []
    assert out["findings"] == ["readout_nonlinearity"]
    fs = 2 ** 10 - 1
    (effect,) = out["effects"]
    at_fs = effect["params"]["deviation_at_full_scale_dn"]
    assert -0.06 * fs < at_fs < -0.015 * fs  # put in: 3 % of full scale, compressive


@pytest.mark.slow
def test_what_the_library_lacks_is_not_a_finding(shared_set):
    """indep-ccd12-offset: an exposure offset with a soft well compression on a CCD-like
    sensor. Whatever diagnose selects is either among what was put in or labelled a stand-in
    with the verdict unexplained (slow: 30-60 s; the diagnose page's shared rows show it)."""
    out = diagnose(read_sweep(shared_set("indep-ccd12-offset")))
    assert set(out["findings"]) <= {"exposure_offset", "pixel_nonlinearity",
                                    "readout_nonlinearity"}
    assert set(out["selected_effects"]) == set(out["findings"]) | set(out["stand_ins"])
    if out["stand_ins"]:
        assert out["unexplained"]
    # no leakage was put in, and one light rate cannot show it (round five)
    assert out["leakage"]["verdict"] in ("cannot tell", "not needed"), out["leakage"]
