"""Fourier coefficients, FRF, coherence, noise and group averages (analysis.frf)."""

import dataclasses

import numpy as np
import pytest
from scipy import stats

from steerlab.analysis.frf import (
    frequency_response,
    group_frequency_response,
    trial_spectra,
)
from steerlab.analysis.periods import select_periods
from tests.analysis.synthetic_trials import ARM, admittance, closed_loop, default_design, make_trial


def numpy_frf(records):
    """The estimator written out plainly: FFT per period, sums over bins, periods, records."""
    d = default_design()
    num = np.zeros(31, complex)
    den = np.zeros(31, complex)
    pp = np.zeros(31)
    tt = np.zeros(31)
    for rec in records:
        sel = select_periods(rec)
        for k in range(sel.n_periods):
            a = sel.start + k * sel.period_samples
            b = a + sel.period_samples
            ramp = np.arange(b - a) / (b - a)

            def periodic(x, a=a, b=b, ramp=ramp):  # less the jump to the next sample, if any
                return x[a:b] - ((x[b] - x[a]) * ramp if b < len(x) else 0.0)

            tp = np.fft.fft(rec.perturbation_torque_Nm[a:b])[d.bins]
            td = np.fft.fft(periodic(rec.driver_torque_Nm))[d.bins]
            th = np.fft.fft(periodic(rec.wheel_angle_rad))[d.bins]
            np.add.at(num, d.band_of_bin, np.conj(tp) * th)
            np.add.at(den, d.band_of_bin, np.conj(tp) * td)
            np.add.at(pp, d.band_of_bin, np.abs(tp) ** 2)
            np.add.at(tt, d.band_of_bin, np.abs(th) ** 2)
    return num / den, np.abs(num) / np.sqrt(pp * tt)


def test_frf_and_coherence_equal_a_plain_numpy_computation():
    recs = [
        make_trial(fs_hz=200.0, run_in_s=3.0, n_periods=2, remnant_sd=0.4, seed=s, repetition=s)
        for s in (1, 2)
    ]
    frf = frequency_response([trial_spectra(r) for r in recs])
    H, coh = numpy_frf(recs)
    np.testing.assert_allclose(frf.H, H, rtol=1e-10)
    np.testing.assert_allclose(frf.coherence, coh, rtol=1e-10)
    assert frf.n_averaged.tolist() == [2 * 2 * 2] * 31  # bins × periods × repetitions
    assert frf.trials == ("S01_BT12_rep1", "S01_BT12_rep2")


def test_noise_free_single_bin_bands_give_the_analytic_admittance():
    d = default_design()
    single = dataclasses.replace(d, band_of_bin=np.arange(len(d.bins)))
    rec = make_trial(design=single, fs_hz=1000.0, run_in_s=2.0)
    frf = frequency_response(trial_spectra(rec))
    np.testing.assert_allclose(frf.frequencies_hz, d.frequencies_hz)
    np.testing.assert_allclose(frf.H, admittance(ARM, d.frequencies_hz), rtol=1e-9)
    np.testing.assert_allclose(frf.coherence, 1.0, rtol=1e-12)


def test_noise_free_double_bands_mix_the_two_bins_as_the_estimator_says():
    # For a noise-free loop the band estimate is Σ a_b² G_θ(f_b) / Σ a_b² G_Td(f_b): each bin's
    # admittance weighted by its share of S(Tp,Td). Computed here from the closed loop.
    d = default_design()
    rec = make_trial(fs_hz=1000.0, run_in_s=2.0)
    frf = frequency_response(trial_spectra(rec))
    sys = closed_loop(ARM)
    G = np.array(
        [
            sys.C @ np.linalg.solve(2j * np.pi * f * np.eye(4) - sys.A, sys.B[:, 0])
            for f in d.frequencies_hz
        ]
    )
    a2 = d.amplitudes_nm**2
    num = np.bincount(d.band_of_bin, a2 * G[:, 0].real) + 1j * np.bincount(
        d.band_of_bin, a2 * G[:, 0].imag
    )
    den = np.bincount(d.band_of_bin, a2 * G[:, 1].real) + 1j * np.bincount(
        d.band_of_bin, a2 * G[:, 1].imag
    )
    np.testing.assert_allclose(frf.H, num / den, rtol=1e-9)
    # … which the reported bin weights reproduce …
    mixed = np.sum(frf.bin_weights * admittance(ARM, frf.bin_frequencies_hz), axis=1)
    np.testing.assert_allclose(frf.H, mixed, rtol=1e-9)
    # … and which is within 1 % of H at the band's mean frequency (the paper's reading).
    np.testing.assert_allclose(frf.H, admittance(ARM, frf.frequencies_hz), rtol=1e-2)
    assert frf.coherence.min() > 0.999


def test_run_in_is_not_used():
    clean = make_trial(fs_hz=200.0, run_in_s=4.0, transient=True)
    dirty = make_trial(fs_hz=200.0, run_in_s=4.0, transient=True)
    dirty.wheel_angle_rad[:800] += 5.0  # garbage during the run-in
    dirty.driver_torque_Nm[:800] -= 50.0
    a = frequency_response(trial_spectra(clean)).H
    b = frequency_response(trial_spectra(dirty)).H
    np.testing.assert_array_equal(a, b)


def test_start_up_transient_is_gone_after_the_default_run_in():
    rec = make_trial(fs_hz=1000.0, run_in_s=2.0, transient=True, known_start=False)
    frf = frequency_response(trial_spectra(rec))
    mixed = np.sum(frf.bin_weights * admittance(ARM, frf.bin_frequencies_hz), axis=1)
    np.testing.assert_allclose(frf.H, mixed, rtol=2e-3)


def test_imported_style_250_hz_off_period_start_without_design():
    rec = make_trial(fs_hz=250.0, run_in_s=7.0, phase_s=17.3, known_start=False, with_design=False)
    s = trial_spectra(rec)
    assert s.excitation.origin == "detected"
    frf = frequency_response(s)
    mixed = np.sum(frf.bin_weights * admittance(ARM, frf.bin_frequencies_hz), axis=1)
    np.testing.assert_allclose(frf.H, mixed, rtol=1e-9)


def test_noise_levels_and_the_variance_of_h_are_calibrated():
    # Over seeds and bands, the squared errors of Ĥ must add up to its predicted variances.
    # (Ratio of sums, not mean of ratios: with 4 noise bins per band each variance estimate
    # has 8 degrees of freedom, and E[1/v̂] > 1/v would inflate a mean of ratios by 8/6.)
    err2, var = [], []
    for seed in range(6):
        rec = make_trial(
            fs_hz=200.0, run_in_s=3.0, remnant_sd=0.4, theta_noise_sd=1e-4, td_noise_sd=0.02,
            seed=seed,
        )  # fmt: skip
        frf = frequency_response(trial_spectra(rec))
        truth = np.sum(frf.bin_weights * admittance(ARM, frf.bin_frequencies_hz), axis=1)
        err2.append(np.abs(frf.H - truth) ** 2)
        var.append(frf.H_variance)
        assert np.all(frf.noise_theta_rad2 > 0) and np.all(frf.noise_td_Nm2 > 0)
        assert np.all(frf.noise_theta_rad2 < frf.power_theta_rad2)
    ratio = np.sum(err2) / np.sum(var)
    assert 0.7 < ratio < 1.4, ratio


def test_noise_free_data_have_no_noise():
    frf = frequency_response(trial_spectra(make_trial(fs_hz=200.0, run_in_s=2.0)))
    assert np.all(frf.noise_theta_rad2 < 1e-20 * frf.power_theta_rad2)


def test_remnant_lowers_coherence_most_at_the_lowest_frequencies():
    rec = make_trial(fs_hz=200.0, run_in_s=3.0, remnant_sd=1.0, seed=4)
    coh = frequency_response(trial_spectra(rec)).coherence
    assert np.all((coh > 0) & (coh <= 1))
    assert coh[:4].mean() < np.median(coh)


def test_spectra_at_other_bins_cannot_be_averaged():
    a = trial_spectra(make_trial(fs_hz=200.0, run_in_s=2.0))
    d = default_design()
    other = dataclasses.replace(d, bins=d.bins + 1)
    b = trial_spectra(make_trial(design=other, fs_hz=200.0, run_in_s=2.0, repetition=2))
    with pytest.raises(ValueError, match="other bins"):
        frequency_response([a, b])


def test_non_finite_samples_in_the_analysed_periods_are_an_error():
    rec = make_trial(fs_hz=200.0, run_in_s=2.0)
    rec.wheel_angle_rad[1000] = np.nan
    with pytest.raises(ValueError, match="wheel_angle_rad has non-finite"):
        trial_spectra(rec)


def test_to_dict_has_units_in_its_keys():
    d = frequency_response(trial_spectra(make_trial(fs_hz=200.0, run_in_s=2.0))).to_dict()
    assert {"frequencies_Hz", "magnitude_rad_per_Nm", "phase_deg", "noise_theta_rad2"} <= set(d)
    assert len(d["frequencies_Hz"]) == 31


def _subject_frfs(scales):
    out = []
    for i, k in enumerate(scales):
        arm = dict(ARM, k_i=ARM["k_i"] * k, b_c=ARM["b_c"] / k)
        rec = make_trial(arm, fs_hz=200.0, run_in_s=2.0, subject=f"S{i}")
        out.append(frequency_response(trial_spectra(rec)))
    return out


def test_group_mean_and_intervals():
    frfs = _subject_frfs([0.7, 0.9, 1.0, 1.2, 1.5])
    g = group_frequency_response(frfs, subjects=[f"S{i}" for i in range(5)])
    Hs = np.array([f.H for f in frfs])
    np.testing.assert_allclose(g.H, Hs.mean(0))
    t = stats.t.ppf(0.975, 4)
    half = t * Hs.real.std(0, ddof=1) / np.sqrt(5)
    np.testing.assert_allclose(g.real_ci[0], Hs.real.mean(0) - half)
    np.testing.assert_allclose(
        g.imag_ci[1], Hs.imag.mean(0) + t * Hs.imag.std(0, ddof=1) / np.sqrt(5)
    )
    lm = np.log(np.abs(Hs))
    np.testing.assert_allclose(
        g.magnitude_ci[1], np.exp(lm.mean(0) + t * lm.std(0, ddof=1) / np.sqrt(5))
    )
    assert np.all(g.magnitude_ci[0] < g.magnitude) and np.all(g.magnitude < g.magnitude_ci[1])
    assert np.all(g.phase_ci_deg[0] < g.phase_deg) and np.all(g.phase_deg < g.phase_ci_deg[1])
    np.testing.assert_allclose(g.H_variance, np.sum(np.abs(Hs - g.H) ** 2, 0) / 20)
    assert g.to_dict()["n_subjects"] == 5


def test_group_of_one_subject_has_no_interval():
    g = group_frequency_response(_subject_frfs([1.0]))
    np.testing.assert_allclose(g.H, g.subject_H[0])
    assert np.all(np.isnan(g.magnitude_ci[0])) and np.all(np.isnan(g.H_variance))


def test_drift_removal_keeps_the_periodic_part_and_removes_a_ramp_exactly():
    from steerlab.analysis.frf import drift_removed, fourier_coefficients
    from steerlab.analysis.periods import PeriodSelection

    P, n_per = 1000, 2
    n = np.arange(P * n_per + 1)
    periodic = np.sin(2 * np.pi * 7 * n / P) + 0.3 * np.cos(2 * np.pi * 31 * n / P + 0.4)
    ramp = 0.002 * n - 0.5  # a drift: jumps by 2 over each period
    sel = PeriodSelection(fs_hz=1000.0, period_samples=P, start=0, n_periods=n_per, origin="test")
    bins = np.array([7, 31, 100])
    want = fourier_coefficients(sel.periods(periodic), bins)
    got = fourier_coefficients(drift_removed(periodic + ramp, sel), bins)
    # Without the removal the ramp leaks 2/(jπk) into bin k: 0.09 at bin 7.
    leaky = fourier_coefficients(sel.periods(periodic + ramp), bins)
    assert np.max(np.abs(leaky - want)) > 0.05
    assert np.max(np.abs(got - want)) < 1e-9
    # The recording ending with the last period: the next sample is extrapolated.
    cut = (periodic + ramp)[: P * n_per]
    got_cut = fourier_coefficients(drift_removed(cut, sel), bins)
    # … the last period, which ends the recording, is left as it is.
    np.testing.assert_allclose(got_cut[1], fourier_coefficients(sel.periods(cut), bins)[1])
    np.testing.assert_allclose(got_cut[0], got[0])


def test_drift_removal_makes_the_high_band_errors_circular_and_honest():
    """Monte-Carlo against the noise model: a random walk (a wandering driver) under a periodic
    response. Without the removal the error at a high bin is one-directional and larger than
    the neighbouring noise bins say; with it, circular and as large as they say."""
    from steerlab.analysis.frf import drift_removed, fourier_coefficients
    from steerlab.analysis.periods import PeriodSelection

    rng = np.random.default_rng(3)
    P = 4000
    sel = PeriodSelection(fs_hz=1000.0, period_samples=P, start=0, n_periods=1, origin="test")
    k, nb = 400, np.array([398, 399, 401, 402])
    errs = {True: [], False: []}
    noise = {True: [], False: []}
    for _ in range(300):
        walk = np.cumsum(rng.normal(0, 1e-3, P + 1)) + rng.normal(0, 1e-6, P + 1)
        for rem in (True, False):
            seg = drift_removed(walk, sel) if rem else sel.periods(walk)
            errs[rem].append(fourier_coefficients(seg, [k])[0, 0])
            noise[rem].append(np.mean(np.abs(fourier_coefficients(seg, nb)) ** 2))
    for rem in (True, False):
        e = np.array(errs[rem]) - np.mean(errs[rem])
        ratio_re_im = np.var(e.real) / np.var(e.imag)
        honest = np.mean(np.abs(e) ** 2) / np.mean(noise[rem])
        if rem:
            assert 0.6 < ratio_re_im < 1.6 and 0.75 < honest < 1.3
        else:  # the leak Δ/(jπk) is purely imaginary here
            assert ratio_re_im < 0.5


def _spectra_with_noise(template, rng, H, G, g, c, sensor=0.0):
    """``template``'s bins with complex-normal remnant spectra written in directly: at every
    bin, excited or not, Td = G·Tp + g·N and θ = H·Td + c·N (+ sensor noise), N ~ CN(0, 1):
    the remnant drives both θ and Td, as in the closed loop."""
    tp = template.tp
    shape, nshape = tp.shape, template.noise_td.shape

    def cn(s):
        return (rng.standard_normal(s) + 1j * rng.standard_normal(s)) / np.sqrt(2)

    n, nn = cn(shape), cn(nshape)
    td = G * tp + g * n
    ntd = g * nn
    return dataclasses.replace(
        template,
        td=td,
        theta=H * td + c * n + sensor * cn(shape),
        noise_td=ntd,
        noise_theta=H * ntd + c * nn + sensor * cn(nshape),
    )


def test_compensated_frf_removes_the_remnants_correlated_error():
    """The remnant drives θ and Td alike, so S_TpTd's noise and Ĥ's error are correlated
    (ρ ≈ 1 in the simulator). A weight that grows with |S_TpTd|² then pulls the error in: the
    |S_TpTd|²-weighted mean error is Σ|Tp|²·c·g / (|a|² + Σ|Tp|²·g²) (analytic, a = E S_TpTd),
    which the maximum-likelihood fit turned into a bias (RT b_i +1.7 %, I_i +0.3 %: 0.4 SEM).
    The compensated estimate with its weight q = |S_TpTd|² − Σ|Tp|²·S_TdTd(noise bins) has a
    q-weighted mean error of 0, and E[q] = |a|²."""
    template = trial_spectra(make_trial(fs_hz=200.0, run_in_s=2.0))
    rng = np.random.default_rng(11)
    H, G = 0.05 - 0.02j, 0.3 + 0.1j
    j, N_DRAWS = 20, 600
    cols = template.excitation.band_of_bin == j
    s_tp = float(np.sum(np.abs(template.tp[:, cols]) ** 2))
    # Td's noise g·N with a share r = 0.1 of |S_TpTd|² at band j (RT has 0.05 near 1 Hz);
    # e = c·N, so ρ = 1, as nearly in the simulator (0.97-0.99).
    g = np.sqrt(0.1 * abs(G) ** 2 * s_tp)
    c = 0.1 * g
    a2 = abs(G * s_tp) ** 2
    r = s_tp * g**2 / a2
    assert 0.03 < r < 0.3, r
    err_plain, err_comp, d2, q = [], [], [], []
    for _ in range(N_DRAWS):
        sp = _spectra_with_noise(template, rng, H, G, g, c)
        fr = frequency_response(sp)
        d = np.sum(np.conj(sp.tp[:, cols]) * sp.td[:, cols])
        d2.append(abs(d) ** 2)
        q.append(abs(d) ** 2 - s_tp * fr.noise_td_Nm2[j])
        err_plain.append(fr.H[j] - H)
        err_comp.append(fr.H_compensated[j] - H)
    d2, q = np.array(d2), np.array(q)
    err_plain, err_comp = np.array(err_plain), np.array(err_comp)
    se = np.sqrt(s_tp * c**2 / a2 / N_DRAWS)  # SE of a mean of N_DRAWS band errors
    weighted_plain = np.sum(d2 * err_plain) / np.sum(d2)
    weighted_comp = np.sum(q * err_comp) / np.sum(q)
    expected = s_tp * c * g / (a2 + s_tp * g**2)
    assert expected > 5 * se  # the effect is real at this noise share …
    assert abs(weighted_plain - expected) < 3 * se  # … the plain ratio shows it …
    assert abs(weighted_comp) < 3 * se  # … and the compensated estimate does not
    assert np.mean(d2) / a2 == pytest.approx(1 + r, abs=0.04)
    assert np.mean(q) / a2 == pytest.approx(1.0, abs=0.04)
