"""Diagnose, round six (issue 53, class dark_outside_well): the generator states a dark signal
outside the photodiode at the multiple of its detection limit that the samples the sensor can
show with it in bear out."""

from __future__ import annotations

import numpy as np

from hsiffc.diagnose import evaluation as ev
from hsiffc.diagnose.effects import truth_terms


def _case(seed):
    spec = ev.class_case_spec(seed)
    assert spec["class"] == "dark_outside_well"
    clean = ev.clean_sweep(spec)
    return spec, clean, truth_terms(clean), ev.class_unit(clean, spec, truth_terms(clean))


def test_the_stated_multiple_holds_on_the_samples_the_sensor_can_show():
    """Development seed 103620 (14 bit, an exposure sweep at one light rate, put in at 30x).
    What the dark signal added to each step is measured on the generated frames (less the clean
    sweep's); on the samples it leaves below 0.9 of full scale, the size put in is the stated
    multiple of the detection limit. The old rule (the multiple of the limit measured on the
    clean samples, those the dark signal pushes out included) put in 26x there."""
    spec, clean, terms, unit = _case(103620)
    sweep, truth = ev.build_case(spec)
    put = truth["effects"][0]
    n = clean.n_frames
    diff = sweep.data.reshape(n, -1).astype(float) - clean.data.reshape(n, -1)
    added = np.stack([diff[clean.step == s].mean(axis=0) for s in terms["steps"]], axis=1)
    fs = float(clean.full_scale_dn)
    pushed = (terms["expected"] < 0.9 * fs) & (terms["expected"] + added >= 0.9 * fs)
    assert pushed[:, terms["light"]].mean() > 0.001  # it pushes a few samples out
    multiple = put["size"] / ev.detection_limit(clean, unit, terms, added=added)
    assert abs(multiple / put["multiple"] - 1.0) < 0.02, multiple
    old = put["multiple"] * ev.detection_limit(clean, unit, terms)
    old_added = added * old / put["size"]
    assert old / ev.detection_limit(clean, unit, terms, added=old_added) < 0.95 * put["multiple"]


def test_no_size_is_found_where_the_leakage_leaves_no_room_above_it():
    """With the leakage set in at 0.8 of full scale (the other classes' sensors), a dark signal
    large enough to be 5x its limit on the clean samples pushes the samples that show it to full
    scale (development seed 100932: 5x there was 1.2x on the samples left): no size up to the
    cap reaches 5x, so this class's sensors leak from 0.45-0.6 of full scale."""
    spec, _, _, _ = _case(100932)
    fs = 2.0 ** spec["bit_depth"] - 1
    assert ev.LEAK_REF_LO * fs <= spec["params"]["leak_ref_dn"] <= ev.LEAK_REF_HI * fs
    spec["params"]["leak_ref_dn"] = 0.8 * fs
    clean = ev.clean_sweep(spec)
    terms = truth_terms(clean)
    unit = ev.class_unit(clean, spec, terms)
    cap = ev.MAX_DARK_OF_FULL_SCALE * fs / terms["t"].max()
    assert 5 * ev.detection_limit(clean, unit, terms) < cap  # the old rule placed it at 5x
    size, limit = ev.dark_size(clean, spec, terms, unit, 5, cap)
    assert size is None and limit > cap / 5


def test_a_spread_shown_by_a_few_standard_deviations_is_pooled():
    """Estimates that spread a little beyond their errors (Cochran's Q 5-20 standard deviations
    above its expectation, as a dark signal outside the photodiode whose pixels differ by 30 %
    shows at one light rate without dark frames: development seeds 111068, 111180, 112188)
    take the sensor's one value; a spread shown by far more (several light rates) is kept."""
    from hsiffc.diagnose.effectfit import POOL_SIGMAS, pool_pixels

    rng = np.random.default_rng(60)
    p = 1024
    a = rng.lognormal(0.0, 1.0, p)
    err = rng.standard_normal(p) / np.sqrt(a)
    for spread, pooled in ((0.25, True), (1.0, False)):
        theta = 2.0 * (1.0 + spread * rng.standard_normal(p)) + err
        mean = (a * theta).sum() / a.sum()
        excess = ((a * (theta - mean) ** 2).sum() - (p - 1)) / np.sqrt(2.0 * (p - 1))
        assert (5.0 < excess < POOL_SIGMAS) if pooled else (excess > POOL_SIGMAS), excess
        assert (np.ptp(pool_pixels(theta, a)) == 0.0) == pooled
