"""Period selection and excited-bin detection (analysis.periods)."""

import dataclasses

import numpy as np
import pytest

from steerlab.analysis.periods import (
    Excitation,
    detect_excitation,
    excitation_from_design,
    find_excitation,
    pair_bins,
    select_periods,
)
from tests.analysis.synthetic_trials import default_design, find_example, load_example, make_trial


def test_recorded_range_gives_the_whole_periods_inside_it():
    rec = make_trial(fs_hz=200.0, run_in_s=4.0, n_periods=2, tail_s=10.0)
    sel = select_periods(rec)
    assert sel.origin == "recorded"
    assert (sel.start, sel.n_periods, sel.period_samples) == (800, 2, 9000)
    assert sel.stop == rec.measured_stop


def test_recorded_range_not_a_whole_number_of_periods_is_truncated():
    rec = make_trial(fs_hz=200.0, run_in_s=4.0, n_periods=2)
    rec.measured_stop = rec.measured_stop - 1  # one sample short of the second period
    sel = select_periods(rec)
    assert (sel.start, sel.n_periods) == (800, 1)


def test_unknown_start_takes_the_periods_that_end_at_the_end():
    rec = make_trial(fs_hz=250.0, run_in_s=7.0, known_start=False, phase_s=13.7)
    sel = select_periods(rec)
    assert sel.origin == "end-aligned"
    assert sel.stop == rec.n_samples
    assert sel.n_periods == 1 and sel.start == 7 * 250


def test_unknown_start_takes_as_many_periods_as_fit_after_the_run_in():
    rec = make_trial(fs_hz=200.0, run_in_s=3.0, n_periods=2, known_start=False)
    assert select_periods(rec).n_periods == 2
    assert select_periods(rec, min_run_in_s=3.5).n_periods == 1


def test_too_short_for_a_period_after_the_run_in_names_the_record():
    rec = make_trial(fs_hz=200.0, run_in_s=1.0, known_start=False)
    with pytest.raises(ValueError, match=rf"{rec.source}.*run-in of at least 2 s"):
        select_periods(rec)
    assert select_periods(rec, min_run_in_s=1.0).n_periods == 1


def test_too_short_recorded_range_is_an_error():
    rec = make_trial(fs_hz=200.0, run_in_s=2.0)
    rec.measured_stop = rec.measured_start + 100
    with pytest.raises(ValueError, match=rf"{rec.source}.*shorter than one perturbation period"):
        select_periods(rec)


def test_period_must_be_a_whole_number_of_samples():
    rec = make_trial(fs_hz=200.0, run_in_s=2.0)
    rec.fs_hz = 200.3
    with pytest.raises(ValueError, match=rf"{rec.source}.*whole number"):
        select_periods(rec)


def test_sample_rate_below_100_hz_is_refused():
    rec = make_trial(fs_hz=200.0, run_in_s=2.0)
    rec.fs_hz = 80.0
    with pytest.raises(ValueError, match="below 100 Hz"):
        select_periods(rec)


def test_pair_bins_pairs_neighbours_and_keeps_lone_bins():
    assert pair_bins(np.array([3, 4, 7, 9, 10, 11, 20])).tolist() == [0, 0, 1, 2, 2, 3, 4]


def test_noise_bins_are_the_nearest_unexcited_bins():
    exc = Excitation(45.0, np.array([3, 4, 7, 8]), np.array([0, 0, 1, 1]), "test")
    nb = exc.noise_bins(2, nyquist_bin=100)
    assert nb[0].tolist() == [1, 2, 5, 6]
    assert nb[1].tolist() == [5, 6, 9, 10]


def test_design_bins_are_used_when_the_record_has_a_design():
    rec = make_trial(fs_hz=200.0, run_in_s=2.0)
    exc = find_excitation(rec, select_periods(rec))
    d = default_design()
    assert exc.origin == "design"
    assert exc.bins.tolist() == d.bins.tolist()
    assert exc.n_bands == 31
    np.testing.assert_allclose(exc.band_frequencies_hz, d.frequencies_hz.reshape(-1, 2).mean(1))


@pytest.mark.parametrize("fs", [200.0, 250.0, 1000.0])
def test_detection_without_a_design_finds_the_design_bins(fs):
    rec = make_trial(
        fs_hz=fs, run_in_s=3.0, known_start=False, with_design=False, phase_s=21.0,
        remnant_sd=0.3, seed=3,
    )  # fmt: skip
    exc = find_excitation(rec, select_periods(rec))
    ref = excitation_from_design(default_design())
    assert exc.origin == "detected"
    assert exc.bins.tolist() == ref.bins.tolist()
    assert exc.band_of_bin.tolist() == ref.band_of_bin.tolist()


def test_detection_survives_a_noisy_measured_perturbation():
    rec = make_trial(fs_hz=200.0, run_in_s=3.0, n_periods=2, with_design=False)
    rng = np.random.default_rng(1)
    rec.perturbation_torque_Nm = rec.perturbation_torque_Nm + 0.05 * rng.standard_normal(
        rec.n_samples
    )
    exc = find_excitation(rec, select_periods(rec))
    assert exc.bins.tolist() == default_design().bins.tolist()


def test_detection_of_lone_bins():
    n = 900
    t = np.arange(n)
    x = np.sin(2 * np.pi * 5 * t / n) + 0.3 * np.sin(2 * np.pi * 40 * t / n + 1)
    x += np.sin(2 * np.pi * 41 * t / n)
    exc = detect_excitation(x[None, :], 9.0)
    assert exc.bins.tolist() == [5, 40, 41]
    assert exc.band_of_bin.tolist() == [0, 1, 1]


def test_a_zero_perturbation_is_an_error():
    with pytest.raises(ValueError, match="nothing excited"):
        detect_excitation(np.zeros((1, 900)), 9.0)


def test_shared_example_gives_31_double_bands_from_3_to_900():
    path = find_example()
    if path is None:
        pytest.skip("shared interchange example not found (set STEERLAB_EXAMPLES)")
    rec = load_example(path)
    sel = select_periods(rec)
    assert (sel.n_periods, sel.period_samples, sel.stop) == (1, 11250, rec.n_samples)
    exc = find_excitation(rec, sel)
    assert exc.n_bands == 31
    assert np.all(np.bincount(exc.band_of_bin) == 2)
    assert (exc.bins.min(), exc.bins.max()) == (3, 900)


def test_a_gap_in_the_time_stamps_is_an_error():
    rec = make_trial(fs_hz=200.0, run_in_s=2.0)
    rec.time_s = rec.time_s.copy()
    rec.time_s[5000:] += 0.5  # half a second lost by an importer
    with pytest.raises(ValueError, match=r"not sampled at 200 Hz.*after sample 4999"):
        select_periods(rec)


def test_a_design_that_does_not_match_the_signal_is_refused():
    d = default_design()
    rec = make_trial(fs_hz=200.0, run_in_s=2.0)
    rec.design = dataclasses.replace(d, bins=d.bins + 1)
    with pytest.raises(ValueError, match="design does not match its perturbation signal"):
        find_excitation(rec, select_periods(rec))


def test_a_design_with_two_wrong_high_bins_is_refused_but_noise_is_tolerated():
    d = default_design()
    rec = make_trial(fs_hz=200.0, run_in_s=2.0)
    rng = np.random.default_rng(0)
    rec.perturbation_torque_Nm = rec.perturbation_torque_Nm + 0.05 * rng.standard_normal(
        rec.n_samples
    )
    assert find_excitation(rec, select_periods(rec)).origin == "design"
    bins = d.bins.copy()
    bins[-2:] += 3
    rec.design = dataclasses.replace(d, bins=bins)
    with pytest.raises(ValueError, match="does not match"):
        find_excitation(rec, select_periods(rec))
