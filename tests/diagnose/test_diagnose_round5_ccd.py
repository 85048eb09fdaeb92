"""Diagnose, round five (issue 53): a linear sensor with an exposure offset (light collected for
longer than the nominal exposure) and a soft compression of the well as it fills, the physics
of the shared set ``indep-ccd12-offset``. Its own seed stream (from ``CLASS2_SEED0``), written
from its own physics; a per-pixel leakage shape took most of the offset and the compression,
so the offset was not found and leakage was called needed on a sensor without any."""

from __future__ import annotations

import json

import numpy as np
import pytest

from hsiffc.diagnose import evaluation as ev


def test_the_stream_is_seeded_split_and_leaves_the_other_streams_alone():
    seeds = ev.seeds("all", 0, 0, 16)
    assert seeds == list(range(ev.CLASS2_SEED0, ev.CLASS2_SEED0 + 16))
    assert ev.seeds("dev", 4, 0, 4) == [0, 2, ev.CLASS2_SEED0, ev.CLASS2_SEED0 + 2]
    specs = [ev.case_spec(s) for s in seeds]
    assert all(s["round"] == 5 and not s["leaky"] for s in specs)
    for half in ("dev", "eval"):
        assert {s["class"] for s in specs if s["half"] == half} == set(ev.CCD_KINDS)
    # both halves hold each kind in turn
    assert [s["class"] for s in specs[:8:2]] == list(ev.CCD_KINDS)
    assert ev.case_spec(ev.CLASS2_SEED0 + 3) == ev.case_spec(ev.CLASS2_SEED0 + 3)
    # an offset at one light level is drawn with darks (without them it is a dark level)
    for s in specs:
        if "offset" in s["class"] and s["n_rates"] == 1:
            assert s["darks"]
    # the other streams draw what they drew
    assert "round" not in ev.case_spec(5)
    assert ev.case_spec(ev.CLASS_SEED0 + 1)["round"] == 3


def test_a_case_is_built_the_same_twice_with_the_effects_at_5x_or_more():
    spec = ev.case_spec(ev.CLASS2_SEED0 + 6)  # an offset and a compression
    a, truth = ev.build_case(spec)
    b, _ = ev.build_case(spec)
    assert np.array_equal(a.data, b.data) and a.data.shape[1:] == ev.SHAPE
    assert [e["name"] for e in truth["effects"]] == ["exposure_offset", "readout_nonlinearity"]
    assert all(e["multiple"] >= 5 for e in truth["effects"])
    assert truth["t0_ms"] > 0 and truth["compression"] > 0
    # the same sweep without the effects: the light frames differ, the darks do not
    clean = ev.ccd_sweep({**spec, "t0_of_max": 0.0, "compression": 0.0})[0]
    light = a.kind == "light"
    assert (a.data[light] != clean.data[light]).any()
    assert np.array_equal(a.data[~light], clean.data[~light])
    assert a.data.max() <= a.full_scale_dn


def test_the_stream_is_scored_on_its_own():
    def case(seed, what, selected, leakage):
        truth = {"class": what, "stream": 5, "kind": "single", "effects": []}
        found = {"selected": selected, "unexplained": False, "leakage": leakage,
                 "ambiguous": [], "runtime_s": 1.0}
        return {"case": {"seed": seed, "n_rates": 1, "darks": True, "n_frames": 2},
                "truth": truth, "found": found, **ev.ccd_verdict(truth, found)}

    results = [case(1, "exposure_offset", ["exposure_offset"], "cannot tell"),
               case(3, "well_compression", ["readout_nonlinearity"], "needed"),
               case(5, "clean_linear", [], "not needed")]
    assert [r["right"] for r in results] == [True, False, True]
    summary = ev.summarise(results)
    assert summary["scores"]["named_right_5x"]["n"] == 0  # not mixed into the first streams
    assert summary["ccd"]["well_compression"]["leakage_claimed"] == 1
    text = ev.markdown(summary, [], "how")
    assert "| well compression | 0 % (0/1) | 1/1 |" in text
    json.dumps(summary)


@pytest.mark.parametrize("seed", [ev.CLASS2_SEED0 + 14])
def test_an_offset_and_a_compression_at_one_light_level_are_found_without_leakage(seed):
    """Development seed 200014: a 10-bit linear sensor, one light level, darks at every
    exposure, an offset and a compression each at about 5x its detection limit. The offset
    and a readout nonlinearity are named, and leakage is not called needed (one light rate:
    it cannot be told from a compression that depends on the signal alone)."""
    r = ev.run_case(seed)
    found = r["found"]
    assert sorted(found["selected"]) == ["exposure_offset", "readout_nonlinearity"], found
    assert found["leakage"] in ("cannot tell", "not needed")
    assert not found["unexplained"] and r["right"]
