"""Tests of hsiffc.spectral: band responses, IMEC XML reader, illumination and electron rates."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import constants

from hsiffc.errors import DataFormatError
from hsiffc.data.mosaic import Mosaic
from hsiffc.spectral import (DEFAULT_GRID, BandSet, Illumination, blackbody, cie_illuminant,
                             colorchecker_reflectances, electron_rate, fabry_perot_bands,
                             gaussian_responses, imec_4x4_visible, imec_5x5_nir, lamp,
                             paper_8band, read_imec_xml, spectral_correction_matrix)

FINE = np.arange(400.0, 1000.0001, 0.05)
from testfiles import synthetic_imec_xml


def measured_fwhm(wl, r):
    """FWHM of the highest peak of ``r`` by linear interpolation of the half-maximum crossings."""
    j = int(np.argmax(r))
    half = r[j] / 2.0
    lo = j
    while r[lo] > half:
        lo -= 1
    hi = j
    while r[hi] > half:
        hi += 1
    left = np.interp(half, [r[lo], r[lo + 1]], [wl[lo], wl[lo + 1]])
    right = np.interp(half, [r[hi], r[hi - 1]], [wl[hi], wl[hi - 1]])
    return right - left


def trapz(y, x):
    return float(np.sum((y[1:] + y[:-1]) * np.diff(x)) / 2.0)


# -- Fabry-Perot bands -----------------------------------------------------------------------------

@pytest.mark.parametrize("centre, fwhm, order", [(650.0, 5.0, 1), (800.0, 10.0, 1),
                                                 (520.0, 3.0, 2), (900.0, 25.0, 1)])
def test_fwhm_exact_on_fine_grid(centre, fwhm, order):
    b = fabry_perot_bands([centre], fwhm, order=order, wavelengths_nm=FINE)
    assert measured_fwhm(FINE, b.responses[0]) == pytest.approx(fwhm, abs=0.01)
    assert FINE[np.argmax(b.responses[0])] == pytest.approx(centre, abs=0.05)


def test_fwhm_on_default_grid_within_resolution():
    centres = np.linspace(600, 875, 25)
    fwhm = np.linspace(4.0, 20.0, 25)
    b = fabry_perot_bands(centres, fwhm)
    for r, f in zip(b.responses, fwhm):
        assert measured_fwhm(DEFAULT_GRID, r) == pytest.approx(f, abs=0.5)


@settings(max_examples=40, deadline=None)
@given(centre=st.floats(450.0, 950.0), fwhm=st.floats(2.0, 40.0), order=st.integers(1, 3))
def test_fwhm_property(centre, fwhm, order):
    wl = np.arange(centre - 5 * fwhm, centre + 5 * fwhm, fwhm / 200.0)
    b = fabry_perot_bands([centre], fwhm, order=order, wavelengths_nm=wl)
    assert measured_fwhm(wl, b.responses[0]) == pytest.approx(fwhm, rel=2e-3)


def test_peak_qe_per_band_and_line_shape_is_not_gaussian():
    b = fabry_perot_bands([600.0, 700.0], [5.0, 8.0], peak_qe=[0.2, 0.6], wavelengths_nm=FINE)
    assert b.responses.max(axis=1) == pytest.approx([0.2, 0.6], rel=1e-6)
    assert b.n_bands == 2 and b.centres_nm.tolist() == [600.0, 700.0]
    assert b.fwhm_nm.tolist() == [5.0, 8.0]
    # two FWHM away from the centre: Lorentzian ~ 1/17 of the peak, Gaussian ~ 2**-16
    at = np.interp(610.0, FINE, b.responses[0]) / 0.2
    assert 0.03 < at < 0.08
    assert np.all(b.responses >= 0)


@pytest.mark.parametrize("centre, order", [(900.0, 1), (750.0, 2), (960.0, 3)])
def test_second_order_lobe_position_and_amplitude(centre, order):
    b = fabry_perot_bands([centre], 10.0, peak_qe=0.4, second_order=0.25, order=order,
                          wavelengths_nm=FINE)
    r = b.responses[0]
    lobe_wl = centre * order / (order + 1)
    near = np.abs(FINE - lobe_wl) < 30
    j = np.argmax(np.where(near, r, -1.0))
    assert FINE[j] == pytest.approx(lobe_wl, abs=0.05)
    assert r[j] == pytest.approx(0.4 * 0.25, rel=1e-3)
    # without the lobe there is (almost) nothing there
    b0 = fabry_perot_bands([centre], 10.0, peak_qe=0.4, order=order, wavelengths_nm=FINE)
    assert b0.responses[0][j] < 1e-3
    # no other interference order is kept
    further = centre * order / (order + 2)
    if further > 400:
        assert np.interp(further, FINE, r) < 1e-3


def test_fabry_perot_rejects_bad_arguments():
    with pytest.raises(ValueError, match="too wide"):
        fabry_perot_bands([500.0], 400.0)
    with pytest.raises(ValueError, match="order"):
        fabry_perot_bands([500.0], 5.0, order=0)
    with pytest.raises(ValueError, match="fwhm_nm"):
        fabry_perot_bands([500.0, 600.0], [5.0, 6.0, 7.0])
    with pytest.raises(ValueError, match="fwhm_nm"):
        fabry_perot_bands([500.0], -1.0)


@pytest.mark.parametrize("factory, n, lo, hi", [(paper_8band, 8, 470, 890),
                                                (imec_4x4_visible, 16, 470, 620),
                                                (imec_5x5_nir, 25, 600, 875)])
def test_presets(factory, n, lo, hi):
    b = factory()
    assert b.n_bands == n
    assert b.centres_nm[0] == pytest.approx(lo) and b.centres_nm[-1] == pytest.approx(hi)
    assert np.all(np.diff(b.centres_nm) > 0)
    assert np.abs(DEFAULT_GRID[np.argmax(b.responses, axis=1)] - b.centres_nm).max() <= 1.0
    assert factory(peak_qe=0.1).responses.max() == pytest.approx(0.1, rel=1e-3)


# -- BandSet ---------------------------------------------------------------------------------------

def test_bandset_dict_round_trip_and_resample():
    b = imec_4x4_visible()
    d = json.loads(json.dumps(b.to_dict()))
    assert BandSet.from_dict(d) == b
    wl = np.arange(450.0, 650.0, 0.5)
    rb = b.resample(wl)
    assert rb.responses.shape == (16, wl.size)
    assert np.allclose(rb.responses[:, ::2], b.responses[:, 50:250])
    outside = b.resample(np.arange(300.0, 1100.0, 1.0))
    assert np.all(outside.responses[:, :100] == 0) and np.all(outside.responses[:, -99:] == 0)
    with pytest.raises(ValueError):
        b.responses[0, 0] = 1.0


def test_bandset_validation():
    with pytest.raises(ValueError, match="responses"):
        BandSet(DEFAULT_GRID, np.zeros((2, 10)), [1, 2], [1, 1])
    with pytest.raises(ValueError, match="centres_nm"):
        BandSet(DEFAULT_GRID, np.zeros((2, DEFAULT_GRID.size)), [1], [1, 1])
    with pytest.raises(ValueError, match="increasing"):
        BandSet(DEFAULT_GRID[::-1], np.zeros((1, DEFAULT_GRID.size)), [1], [1])
    with pytest.raises(ValueError, match="missing"):
        BandSet.from_dict({"responses": []})


# -- illumination ----------------------------------------------------------------------------------

@pytest.mark.parametrize("spec", ["2200K", "2900 K", "lamp A", "lamp B", "D65", "A", "FL2"])
@pytest.mark.parametrize("irr", [0.05, 12.5])
def test_irradiance_scaling(spec, irr):
    il = lamp(spec, irr)
    assert trapz(il.spectral_irradiance, il.wavelengths_nm) == pytest.approx(irr, rel=1e-9)
    assert il.irradiance_w_m2 == pytest.approx(irr, rel=1e-9)
    assert np.all(il.spectral_irradiance >= 0)


def test_irradiance_scaling_custom_grid_and_rescale():
    wl = np.linspace(450.0, 900.0, 91)
    il = blackbody(3100, 2.0, wavelengths_nm=wl)
    assert trapz(il.spectral_irradiance, wl) == pytest.approx(2.0, rel=1e-9)
    assert il.scaled(5.0).irradiance_w_m2 == pytest.approx(5.0)
    il2 = cie_illuminant("D65", 1.0, wavelengths_nm=np.array([400.0, 410.0, 450.0, 900.0]))
    assert il2.irradiance_w_m2 == pytest.approx(1.0)


def test_warmer_lamp_is_redder():
    def red_blue(il):
        return np.interp(700, il.wavelengths_nm, il.spectral_irradiance) / \
            np.interp(450, il.wavelengths_nm, il.spectral_irradiance)
    assert red_blue(lamp("2200K", 1.0)) > 1.5 * red_blue(lamp("2900K", 1.0))
    assert red_blue(lamp("lamp B", 1.0)) == pytest.approx(red_blue(lamp("2200 K", 1.0)))
    assert red_blue(lamp("lamp A", 1.0)) == pytest.approx(red_blue(lamp("2900k", 1.0)))


@pytest.mark.parametrize("t", [2200.0, 2900.0, 5000.0])
def test_blackbody_matches_planck(t):
    il = blackbody(t, 1.0)
    lam = DEFAULT_GRID * 1e-9
    planck = 1.0 / (lam ** 5 * np.expm1(constants.h * constants.c / (lam * constants.k * t)))
    planck *= 1.0 / trapz(planck, DEFAULT_GRID)
    assert np.allclose(il.spectral_irradiance, planck, rtol=2e-3)


def test_cie_a_matches_2856k_blackbody():
    a = cie_illuminant("A", 1.0).spectral_irradiance
    bb = blackbody(2856, 1.0).spectral_irradiance
    assert np.allclose(a, bb, rtol=0.01)


def test_cie_extrapolation_is_continuous():
    d65 = cie_illuminant("d65", 1.0)          # case-insensitive; table ends at 780 nm
    e = d65.spectral_irradiance
    i = int(np.searchsorted(DEFAULT_GRID, 780.0))
    assert e[i + 1] / e[i] == pytest.approx(1.0, abs=0.03)
    assert np.all(e[i:] > 0) and np.all(np.diff(e[i + 1:]) < 0)   # Planck tail at 6500 K
    f2 = lamp("F2", 1.0)                      # old spelling of FL2
    assert f2.label == "CIE FL2"
    assert f2.spectral_irradiance[DEFAULT_GRID > 780].sum() < 0.05 * f2.spectral_irradiance.sum()


def test_unknown_lamp_lists_valid_names():
    with pytest.raises(ValueError) as exc:
        lamp("sodium", 1.0)
    msg = str(exc.value)
    for name in ("'sodium'", "lamp A", "lamp B", "2200K", "D65", "FL2"):
        assert name in msg
    with pytest.raises(ValueError, match="D65"):
        cie_illuminant("D66", 1.0)


def test_illumination_validation():
    with pytest.raises(ValueError, match="irradiance"):
        blackbody(2900, -1.0)
    with pytest.raises(ValueError, match="cct_k"):
        blackbody(0, 1.0)
    with pytest.raises(ValueError, match="vignetting"):
        lamp("lamp A", 1.0, vignetting=1.0)
    il = lamp("lamp A", 1.0, vignetting=0.2)
    assert Illumination.from_dict(json.loads(json.dumps(il.to_dict()))) == il


def test_spatial_gain():
    assert np.all(lamp("lamp A", 1.0).spatial_gain((6, 9)) == 1.0)
    g = lamp("lamp A", 1.0, vignetting=0.3).spatial_gain((101, 151))
    assert g.shape == (101, 151) and g.max() == 1.0 and g[50, 75] == 1.0
    assert g[0, 0] == pytest.approx(0.7) and g[-1, -1] == pytest.approx(0.7)
    assert np.allclose(g, g[::-1, :]) and np.allclose(g, g[:, ::-1])
    assert np.all(np.diff(g[50, 75:]) < 0)          # falls off monotonically
    g_even = lamp("lamp A", 1.0, vignetting=0.5).spatial_gain((4, 4))
    assert g_even.max() == 1.0 and g_even.min() == pytest.approx(0.5 / g_even.max(), rel=0.2)


# -- electron rate ---------------------------------------------------------------------------------

def test_electron_rate_hand_computed_box_band():
    e0, q, pitch = 1e-3, 0.5, 5.5                      # W m^-2 nm^-1, QE, um
    flat = Illumination("flat", DEFAULT_GRID, np.full(DEFAULT_GRID.size, e0))
    box = np.where((DEFAULT_GRID >= 600) & (DEFAULT_GRID <= 700), q, 0.0)
    bands = BandSet(DEFAULT_GRID, box[None], [650.0], [100.0])
    # sum over the 101 samples 600..700 nm of lambda (zero neighbours: trapezoid = sum * 1 nm)
    sum_lambda_m = 101 * 650e-9
    h, c = 6.62607015e-34, 299792458.0
    expected = (pitch * 1e-6) ** 2 * e0 * q * sum_lambda_m / (h * c) / 1000.0
    got = electron_rate(flat, bands, pixel_pitch_um=pitch)
    assert got.shape == (1,)
    assert got[0] == pytest.approx(expected, rel=1e-9)
    assert got[0] == pytest.approx(5.0e3, rel=0.01)      # ~ 5000 e-/ms


def test_the_si_constants_are_scipys_and_spectral_loads_no_scipy():
    """hsiffc.spectral holds the exact SI h and c itself: importing it (every command that
    touches the flat field or the calibration does) no longer loads scipy."""
    import subprocess
    import sys

    from hsiffc.spectral import radiometry

    assert (radiometry.PLANCK_J_S, radiometry.SPEED_OF_LIGHT_M_S) == (constants.h, constants.c)
    run = subprocess.run([sys.executable, "-c", "import sys, hsiffc.spectral; "
                          "print('scipy' in sys.modules)"], capture_output=True, text=True,
                         timeout=120)
    assert run.returncode == 0, run.stderr[-2000:]
    assert run.stdout.split() == ["False"]


def test_electron_rate_linear_in_irradiance_and_area():
    bands = paper_8band()
    r1 = electron_rate(lamp("lamp A", 0.3), bands, pixel_pitch_um=5.5)
    r3 = electron_rate(lamp("lamp A", 0.9), bands, pixel_pitch_um=5.5)
    r2p = electron_rate(lamp("lamp A", 0.3), bands, pixel_pitch_um=11.0)
    assert r1.shape == (8,) and np.all(r1 > 0)
    assert np.allclose(r3, 3 * r1, rtol=1e-12)
    assert np.allclose(r2p, 4 * r1, rtol=1e-12)


def test_electron_rate_reflectance_shapes():
    bands = imec_5x5_nir()
    il = lamp("D65", 1.0)
    refl, names = colorchecker_reflectances()
    base = electron_rate(il, bands, pixel_pitch_um=5.5)
    half = electron_rate(il, bands, pixel_pitch_um=5.5, reflectance=np.full(601, 0.5))
    assert half.shape == (25,) and np.allclose(half, base / 2)
    many = electron_rate(il, bands, pixel_pitch_um=5.5, reflectance=refl)
    assert many.shape == (24, 25)
    assert np.allclose(many[3], electron_rate(il, bands, pixel_pitch_um=5.5,
                                              reflectance=refl[3]))
    with pytest.raises(ValueError, match="reflectance"):
        electron_rate(il, bands, pixel_pitch_um=5.5, reflectance=np.ones(100))
    with pytest.raises(ValueError, match="pixel_pitch"):
        electron_rate(il, bands, pixel_pitch_um=0)


def test_electron_rate_resamples_bands():
    wl = np.arange(500.0, 900.0, 2.0)
    il = blackbody(2900, 1.0, wavelengths_nm=wl)
    bands = fabry_perot_bands([600.0, 700.0], 20.0)
    got = electron_rate(il, bands, pixel_pitch_um=5.5)
    ref = electron_rate(il, bands.resample(wl), pixel_pitch_um=5.5)
    assert np.allclose(got, ref)


def test_colorchecker_reflectances():
    refl, names = colorchecker_reflectances()
    assert refl.shape == (24, DEFAULT_GRID.size) and len(names) == 24
    assert names[0] == "dark skin" and names[18].startswith("white")
    assert refl.min() >= 0 and refl.max() <= 1
    assert refl[18, 200] > 0.8 and refl[23, 200] < 0.06          # white vs black at 600 nm
    beyond = DEFAULT_GRID > 780
    assert np.all(refl[:, beyond] == refl[:, beyond][:, :1])    # held constant past the table
    r2, _ = colorchecker_reflectances(np.arange(400.0, 701.0, 5.0), dataset="ColorChecker N Ohta")
    assert r2.shape == (24, 61)
    with pytest.raises(ValueError, match="ISO 17321-1"):
        colorchecker_reflectances(dataset="nope")


# -- correction matrix -----------------------------------------------------------------------------

def test_derived_correction_matrix_on_synthetic_bands():
    bands = imec_5x5_nir()
    # virtual bands at the physical band centres: peaks where requested
    m = spectral_correction_matrix(bands, bands.centres_nm, 15.0)
    v = m @ bands.responses
    assert np.abs(DEFAULT_GRID[np.argmax(v, axis=1)] - bands.centres_nm).max() <= 1.0
    # between the bands: within half a band spacing (11.5 nm) and a fair Gaussian shape
    centres = np.arange(615.0, 861.0, 15.0)
    m = spectral_correction_matrix(bands, centres, 15.0)
    assert m.shape == (centres.size, 25)
    v = m @ bands.responses
    assert np.abs(DEFAULT_GRID[np.argmax(v, axis=1)] - centres).max() <= 5.75
    target = gaussian_responses(centres, 15.0)
    assert np.linalg.norm(v - target) / np.linalg.norm(target) < 0.4
    wide = imec_5x5_nir(fwhm_nm=18.0)
    v = spectral_correction_matrix(wide, centres, 15.0) @ wide.responses
    assert np.abs(DEFAULT_GRID[np.argmax(v, axis=1)] - centres).max() <= 3.0
    assert np.linalg.norm(v - target) / np.linalg.norm(target) < 0.2
    # unit invariance and regularisation shrinking the coefficients
    scaled = BandSet(bands.wavelengths_nm, bands.responses * 100, bands.centres_nm, bands.fwhm_nm)
    assert np.allclose(spectral_correction_matrix(scaled, centres, 15.0), m / 100)
    strong = spectral_correction_matrix(bands, centres, 15.0, regularisation=1.0)
    assert np.linalg.norm(strong) < np.linalg.norm(m)


# -- IMEC XML: real file ---------------------------------------------------------------------------

@pytest.fixture(scope="module")
def cal(imec_xml):
    return read_imec_xml(imec_xml)


@pytest.mark.realdata
def test_imec_sensor_and_layout(cal):
    assert (cal.width, cal.height) == (2048, 1088)
    assert cal.input_bpp == 10 and cal.effective_bpp == 9 and cal.adc_gain == 39
    assert cal.pattern_shape == (5, 5) and cal.n_bands == 25
    assert cal.filter_area == (0, 3, 2045, 1080)
    assert cal.pixel_pitch_um is None            # the file says 0
    m = cal.mosaic()
    assert isinstance(m, Mosaic) and m.tile_shape == (5, 5) and m.offset == (3, 0)
    assert m.band_map((8, 5))[3, 0] == 0 and m.band_map((8, 5))[4, 2] == 7
    assert m.wavelengths_nm == pytest.approx(tuple(cal.bands.centres_nm))
    assert m.wavelengths_nm[0] == pytest.approx(614.903, abs=1e-3)   # position 0


@pytest.mark.realdata
def test_imec_bands_and_units(cal):
    b = cal.bands
    assert b.responses.shape == (25, 601) and b.wavelengths_nm[[0, -1]].tolist() == [400, 1000]
    assert np.all((b.centres_nm > 600) & (b.centres_nm < 880))
    peak_at = b.wavelengths_nm[np.argmax(b.responses, axis=1)]
    err = np.abs(peak_at - b.centres_nm)
    assert err.max() < 6.0 and np.sum(err <= 1.5) >= 24
    # percent -> fraction: each vendor peak QE equals the maximum of composition * rejection
    qe = np.array([p[0].qe for p in cal.peaks])
    assert np.allclose(b.responses.max(axis=1), qe, rtol=1e-3)
    assert cal.qe_scale == 0.01 and 0.1 < qe.min() and qe.max() < 1.5
    assert all(p[0].order == 1 for p in cal.peaks)
    # the rejection filter is folded into the responses: nothing left at 400 nm
    assert cal.rejection_filter[0] < 0.01 and cal.rejection_filter[300] > 0.9
    assert np.abs(b.responses[:, 0]).max() < 1e-3
    assert np.allclose(cal.decomposition @ b.responses.T, np.eye(25), atol=0.03)
    rescaled = read_imec_xml(cal.path, max_qe=0.4)
    assert rescaled.bands.responses.max() == pytest.approx(0.4)


@pytest.mark.realdata
def test_imec_correction_matrix_convention(cal):
    assert cal.correction_matrix.shape == (25, 25)
    assert cal.virtual_wavelengths_nm.shape == (25,) and cal.virtual_fwhm_nm == 15
    v = cal.virtual_responses()           # columns ordered by pattern position
    wl = cal.bands.wavelengths_nm
    err = np.abs(wl[np.argmax(v, axis=1)] - cal.virtual_wavelengths_nm)
    assert err.max() <= 4.0 and np.median(err) <= 0.5
    # ordering the bands by wavelength instead breaks it
    order = np.argsort(cal.bands.centres_nm)
    wrong = cal.correction_matrix @ cal.bands.responses[order]
    assert np.median(np.abs(wl[np.argmax(wrong, axis=1)] - cal.virtual_wavelengths_nm)) > 20
    x = np.random.default_rng(0).random((3, 25, 4))
    assert np.allclose(cal.correct(x, axis=1)[1, :, 2], cal.correction_matrix @ x[1, :, 2])


@pytest.mark.realdata
def test_derived_correction_matrix_on_real_bands(cal):
    m = spectral_correction_matrix(cal.bands, cal.virtual_wavelengths_nm, 15.0)
    v = m @ cal.bands.responses
    err = np.abs(cal.bands.wavelengths_nm[np.argmax(v, axis=1)] - cal.virtual_wavelengths_nm)
    assert err.max() <= 4.0 and np.median(err) <= 0.5
    # the vendor matrix targets the same unit-peak Gaussians on the file's percent scale
    vendor = 100 * cal.virtual_responses()
    rel = np.linalg.norm(v - vendor, axis=1) / np.linalg.norm(vendor, axis=1)
    assert rel.max() < 0.2


# -- IMEC XML: bad files ---------------------------------------------------------------------------


def test_minimal_xml_parses_in_position_order(tmp_path):
    p = tmp_path / "good.xml"
    p.write_text(synthetic_imec_xml())
    cal = read_imec_xml(p)
    assert cal.bands.centres_nm.tolist() == [402, 404, 406, 408]   # sorted by position index
    assert cal.bands.responses.max() == pytest.approx(1.0)         # 100 % -> 1, no rejection
    assert cal.pixel_pitch_um == 5.5 and cal.decomposition is None
    assert cal.correction_matrix.shape == (1, 4)
    assert cal.mosaic().offset == (2, 1)
    assert cal.mosaic().pattern.tolist() == [[0, 1], [2, 3]]


@pytest.mark.parametrize("case, content, needle", [
    ("not_xml", "this is not <xml", "not a well-formed XML"),
    ("no_pattern", synthetic_imec_xml(pattern=False), "pattern_width"),
    ("short", synthetic_imec_xml(n_samples=10), "10 samples"),
    ("wrong_root", synthetic_imec_xml(root="camera"), "sensor_calibration"),
    ("bad_number", synthetic_imec_xml().replace("<width>64</width>", "<width>wide</width>"),
     "sensor_info/width"),
    # "²" passes str.isdigit but not int(): the reader must still say which element is bad
    ("superscript_index", synthetic_imec_xml().replace('pattern_position_index="2"',
                                         'pattern_position_index="\u00b2"'),
     "pattern_position_index"),
], ids=["not_xml", "no_pattern", "short", "wrong_root", "bad_number", "superscript_index"])
def test_bad_xml_raises_data_format_error(tmp_path, case, content, needle):
    p = tmp_path / f"{case}.xml"
    p.write_text(content)
    with pytest.raises(DataFormatError) as exc:
        read_imec_xml(p)
    assert str(p) in str(exc.value) and needle in str(exc.value)
    assert exc.value.path == str(p)


def test_non_numeric_element_count_is_ignored_not_a_crash(tmp_path):
    # nr_elements is only cross-checked when it is a number; "²" passes str.isdigit but not
    # int(), and used to escape as a bare ValueError
    odd, plain = tmp_path / "count.xml", tmp_path / "plain.xml"
    odd.write_text(synthetic_imec_xml().replace('nr_elements="4"', 'nr_elements="\u00b2"'))
    plain.write_text(synthetic_imec_xml())
    assert (read_imec_xml(odd).mosaic().pattern.tolist()
            == read_imec_xml(plain).mosaic().pattern.tolist())


def test_missing_xml_file(tmp_path):
    p = tmp_path / "absent.xml"
    with pytest.raises(DataFormatError, match="not found") as exc:
        read_imec_xml(p)
    assert str(p) in str(exc.value)


def test_duplicate_position_index(tmp_path):
    p = tmp_path / "dup.xml"
    p.write_text(synthetic_imec_xml(order=(0, 1, 1, 3)))
    with pytest.raises(DataFormatError, match="repeated"):
        read_imec_xml(p)
