"""The Reduced Power Method multisine: checked on the sampled signal's own spectrum."""

from __future__ import annotations

import numpy as np
import pytest

from steerlab.protocols.perturbation import PerturbationDesign, PerturbationSpec, design_multisine

FS = 1000.0


@pytest.fixture(scope="module")
def design():
    return design_multisine(PerturbationSpec())


@pytest.fixture(scope="module")
def spectrum(design):
    x = design.one_period(FS)
    return x, np.fft.rfft(x) / len(x)


def test_excited_bins_are_31_double_bands_with_gaps(design, spectrum):
    _, X = spectrum
    power = np.abs(X) ** 2
    excited = np.flatnonzero(power > 1e-12 * power.max())
    assert excited.tolist() == design.bins.tolist()
    assert len(excited) == 62
    starts = excited[::2]
    assert np.all(excited[1::2] == starts + 1), "each band is two adjacent bins"
    # At least two unexcited bins between bands, where noise can be measured.
    assert np.all(np.diff(starts) >= 4)
    assert design.frequencies_hz.max() <= 20.0 + 1e-9
    assert design.frequencies_hz.max() > 19.5
    # Log spread: the upper bands are spaced by a roughly constant ratio.
    upper = starts[starts > 40]
    ratios = upper[1:] / upper[:-1]
    assert ratios.std() / ratios.mean() < 0.15
    # Non-excited bins carry nothing (up to floating-point round-off).
    rest = np.setdiff1d(np.arange(1, len(X)), excited)
    assert np.max(power[rest]) < 1e-20


def test_power_ratio_across_07_hz(design, spectrum):
    _, X = spectrum
    amp = 2 * np.abs(X[design.bins])
    f = design.frequencies_hz
    low, high = amp[f <= 0.7], amp[f > 0.7]
    assert np.allclose(low, low[0], rtol=1e-9) and np.allclose(high, high[0], rtol=1e-9)
    assert (high[0] / low[0]) ** 2 == pytest.approx(0.1, rel=1e-9)


def test_sd_within_one_percent_and_crest_factor(design, spectrum):
    x, _ = spectrum
    assert x.std() == pytest.approx(2.26, rel=0.01)
    cf = np.max(np.abs(x)) / x.std()
    assert design.crest_factor == pytest.approx(cf, rel=0.02)
    # Optimised phases beat random ones: compare with the same spectrum, unoptimised.
    rng = np.random.default_rng(1)
    crest_random = []
    for _ in range(20):
        ph = rng.uniform(-np.pi, np.pi, len(design.bins))
        y = PerturbationDesign(
            45.0, design.bins, design.amplitudes_nm, ph, design.band_of_bin
        ).one_period(FS)
        crest_random.append(np.max(np.abs(y)) / y.std())
    assert cf < min(crest_random)
    assert cf < 2.6


def test_reproducible_from_seed_and_stored_design_regenerates_signal(design):
    again = design_multisine(PerturbationSpec())
    assert np.array_equal(again.phases_rad, design.phases_rad)
    other = design_multisine(PerturbationSpec(seed=5))
    assert not np.allclose(other.phases_rad, design.phases_rad)
    back = PerturbationDesign.from_json(design.to_json())
    t = np.arange(0, 90, 1 / 250)  # another sample rate, two periods
    assert np.allclose(back.signal(t), design.signal(t), atol=1e-12)
    assert np.allclose(design.signal(t[: 45 * 250]), design.one_period(250), atol=1e-9)


def test_ratio_is_configurable():
    d = design_multisine(PerturbationSpec(reduced_power_ratio=0.25))
    f = d.frequencies_hz
    r = d.amplitudes_nm[f > 0.7][0] / d.amplitudes_nm[f <= 0.7][0]
    assert r**2 == pytest.approx(0.25)
    assert d.sd_nm == pytest.approx(2.26)


@pytest.mark.parametrize(
    "kw, field",
    [
        ({"sd_nm": -1}, "sd_nm"),
        ({"gap_bins": 0}, "gap_bins"),
        ({"reduced_power_ratio": 0}, "reduced_power_ratio"),
        ({"f_max_hz": 1.0}, "f_max_hz"),
        ({"period_s": 0}, "period_s"),
    ],
)
def test_bad_spec_names_the_field(kw, field):
    with pytest.raises(ValueError, match=field):
        design_multisine(PerturbationSpec(**kw))
