"""LPV models from local arm models, checked against independently written truths."""

from __future__ import annotations

import json
import math
import time

import numpy as np
import pytest

from steerlab.analysis.lpv import (
    DEFAULT_EXCLUSIONS,
    RT_EXCLUSION_REASON,
    DeCaignyLPV,
    LPVModel,
    MeasuredFRF,
    OperatingPoint,
    PhysicalLPV,
    StructureError,
    TimeData,
    analyse_lpv,
    build_lpv,
    fit_percent,
    fit_table,
    leave_one_out,
    simulate,
    vaf,
)

CONDITIONS = ["BT18", "BT12", "BT8", "BT5", "PT"]  # rising grip force
MU = np.array([60.0, 90.0, 120.0, 160.0, 210.0])  # N
F_HZ = np.geomspace(0.08, 20.0, 31)


def truth(p: dict[str, float], f_hz: np.ndarray) -> np.ndarray:
    """H = (I s² + (b_i+b_c) s + (k_i+k_c)) / ((b_c s + k_c)(I s² + b_i s + k_i)), written out
    from the combined form so that it shares no code with analysis.lpv."""
    s = 2j * math.pi * np.asarray(f_hz)
    num = p["I_i"] * s**2 + (p["b_i"] + p["b_c"]) * s + (p["k_i"] + p["k_c"])
    den = (p["b_c"] * s + p["k_c"]) * (p["I_i"] * s**2 + p["b_i"] * s + p["k_i"])
    return num / den


def quadratic_params(mu: float) -> dict[str, float]:
    """Physical parameters that are exactly polynomials (order ≤ 2) in μ."""
    t = (mu - 60.0) / 150.0
    return {
        "I_i": 0.1,
        "b_i": 1.5 + 1.5 * t,
        "k_i": 10.0 + 30.0 * t + 20.0 * t**2,
        "b_c": 2.0 + 3.0 * t**2,
        "k_c": 80.0 + 100.0 * t + 120.0 * t**2,
    }


# Plausible local fits that are NOT polynomial in μ (the realistic case). The zeros are complex
# at every point (b_i + b_c is small next to 2·sqrt(I(k_i + k_c))).
WIGGLY = {
    "I_i": [0.1, 0.1, 0.1, 0.1, 0.1],
    "b_i": [1.5, 2.1, 1.9, 2.6, 3.0],
    "k_i": [10.0, 21.0, 27.0, 47.0, 60.0],
    "b_c": [2.0, 2.9, 3.1, 4.4, 5.0],
    "k_c": [80.0, 140.0, 150.0, 240.0, 300.0],
}
# A set whose zeros are real everywhere (stiff, well-damped contact): the paper's split works.
REAL_ZEROS = {
    "I_i": [0.1, 0.1, 0.1, 0.1, 0.1],
    "b_i": [1.5, 1.9, 2.3, 2.6, 3.0],
    "k_i": [10.0, 22.0, 30.0, 47.0, 60.0],
    "b_c": [6.0, 7.5, 9.0, 10.0, 12.0],
    "k_c": [80.0, 120.0, 170.0, 240.0, 300.0],
}


def table_points(table: dict[str, list[float]], **kw) -> list[OperatingPoint]:
    return [
        OperatingPoint(c, float(m), {k: v[i] for k, v in table.items()}, **kw)
        for i, (c, m) in enumerate(zip(CONDITIONS, MU, strict=True))
    ]


def with_measured_frf(points: list[OperatingPoint], seed: int = 7) -> list[OperatingPoint]:
    """Measured FRFs = local model × (1 + 3 % complex noise), seeded."""
    rng = np.random.default_rng(seed)
    out = []
    for p in points:
        noise = 0.03 * (rng.normal(size=F_HZ.size) + 1j * rng.normal(size=F_HZ.size))
        frf = MeasuredFRF(F_HZ, truth(dict(p.parameters), F_HZ) * (1 + noise), np.ones(F_HZ.size))
        out.append(OperatingPoint(p.condition, p.mu_N, p.parameters, frf))
    return out


# (a) physical interpolation of exactly-polynomial parameters -------------------------------


def test_physical_interpolation_is_exact_for_polynomial_parameters() -> None:
    pts = [OperatingPoint(c, m, quadratic_params(m)) for c, m in zip(CONDITIONS, MU, strict=True)]
    model = PhysicalLPV.fit(pts, order=2)
    for mu in np.linspace(MU[0], MU[-1], 37):  # operating points and everything between
        expected = quadratic_params(mu)
        got = model.parameters(mu)
        for k in expected:
            assert got[k] == pytest.approx(expected[k], rel=1e-10, abs=1e-12)
        np.testing.assert_allclose(
            model.frequency_response(mu, F_HZ), truth(expected, F_HZ), rtol=1e-10
        )
        num, den = model.transfer_function(mu)
        s = 2j * math.pi * F_HZ
        np.testing.assert_allclose(
            np.polyval(num, s) / np.polyval(den, s), truth(expected, F_HZ), rtol=1e-10
        )
    assert model.parameters(100.0)["I_i"] == 0.1  # held constant, stays exactly constant


def test_out_of_range_policies() -> None:
    pts = [OperatingPoint(c, m, quadratic_params(m)) for c, m in zip(CONDITIONS, MU, strict=True)]
    clip = PhysicalLPV.fit(pts)
    assert clip.parameters(300.0) == clip.parameters(210.0)
    assert clip.parameters(10.0) == clip.parameters(60.0)
    ext = PhysicalLPV.fit(pts, out_of_range="extrapolate")
    assert ext.parameters(250.0)["k_c"] == pytest.approx(quadratic_params(250.0)["k_c"])
    with pytest.raises(ValueError, match="outside"):
        PhysicalLPV.fit(pts, out_of_range="raise").parameters(211.0)
    with pytest.raises(ValueError, match="NaN"):
        clip.parameters(float("nan"))


# (b) the de Caigny decomposition recomposes the local models exactly ------------------------


@pytest.mark.parametrize(("table", "structure"), [(WIGGLY, "second_order"), (REAL_ZEROS, "split")])
def test_de_caigny_recomposes_local_models(table: dict, structure: str) -> None:
    pts = table_points(table)
    model = DeCaignyLPV.fit(pts, order=len(pts) - 1)  # interpolating polynomials
    assert model.structure == structure
    for p in pts:
        h = truth(dict(p.parameters), F_HZ)
        np.testing.assert_allclose(model.frequency_response(p.mu_N, F_HZ), h, rtol=1e-9)
        # The series state-space realisation, evaluated as C(sI − A)⁻¹B + D, agrees too.
        np.testing.assert_allclose(model.state_space(p.mu_N).frequency_response(F_HZ), h, rtol=1e-9)
        num, den = model.transfer_function(p.mu_N)
        s = 2j * math.pi * F_HZ
        np.testing.assert_allclose(np.polyval(num, s) / np.polyval(den, s), h, rtol=1e-9)


def test_blocks_are_observable_canonical_and_pair_the_contact_pole() -> None:
    pts = table_points(REAL_ZEROS)
    model = DeCaignyLPV.fit(pts, order=4, zeros="split")
    for p in pts:
        I, bi, ki = (p.parameters[k] for k in ("I_i", "b_i", "k_i"))
        bc, kc = p.parameters["b_c"], p.parameters["k_c"]
        sub = model.subsystems(p.mu_N)
        np.testing.assert_allclose(sub.gain, 1.0 / bc)
        np.testing.assert_allclose(sub.second.A, [[-bi / I, 1.0], [-ki / I, 0.0]])
        np.testing.assert_allclose(sub.second.C, [[1.0, 0.0]])
        assert sub.first.A[0, 0] == pytest.approx(-kc / bc)
        # F = (s − z_F)/(s − p): its zero is the numerator root nearer the contact pole.
        z_first = sub.first.A[0, 0] - sub.first.B[0, 0]
        zeros = np.roots([I, bi + bc, ki + kc]).real
        nearest = zeros[np.argmin(np.abs(np.log(np.abs(zeros) / (kc / bc))))]
        assert z_first == pytest.approx(nearest)
        z_second = -sub.second.B[1, 0]
        assert sorted([z_first, z_second]) == pytest.approx(sorted(zeros))


def test_complex_zeros_cannot_be_split() -> None:
    pts = table_points(WIGGLY)
    with pytest.raises(StructureError, match="complex"):
        DeCaignyLPV.fit(pts, zeros="split")
    auto = DeCaignyLPV.fit(pts)
    assert auto.structure == "second_order"
    assert "complex" in auto.structure_reason
    assert auto.to_dict()["local_pole_zero"][0]["zeros_real"] is False


def test_intrinsic_poles_turning_real_are_handled() -> None:
    table = dict(WIGGLY, b_i=[1.5, 2.5, 3.5, 5.0, 6.0])  # b_i² > 4 I k_i from BT8 up
    pts = table_points(table)
    summary = DeCaignyLPV.fit(pts).to_dict()["local_pole_zero"]
    assert [s["intrinsic_poles_real"] for s in summary] == [False, False, True, True, True]
    for method in ("de_caigny", "physical"):
        model = build_lpv(pts, method, order=4)
        for p in pts:
            np.testing.assert_allclose(
                model.frequency_response(p.mu_N, F_HZ), truth(dict(p.parameters), F_HZ), rtol=1e-9
            )
        # Smooth in between: no jump where the pair turns real.
        mus = np.linspace(MU[0], MU[-1], 200)
        mag = np.array([abs(model.frequency_response(m, [1.0])[0]) for m in mus])
        assert np.max(np.abs(np.diff(np.log(mag)))) < 0.05


# (c) leave-one-out -------------------------------------------------------------------------


def test_leave_one_out_is_worse_than_in_sample() -> None:
    pts = with_measured_frf(table_points(WIGGLY))
    report = leave_one_out(pts, frequencies_hz=F_HZ)
    assert report.not_left_out.keys() == {"BT18", "PT"}
    assert len(report.results) == 2 * 3  # two methods × BT12, BT8, BT5
    for r in report.results:
        assert r.condition in {"BT12", "BT8", "BT5"}
        assert r.condition not in r.trained_on and len(r.trained_on) == 4
        assert r.fit_vs_local_percent < r.in_sample_fit_vs_local_percent
        assert r.fit_vs_measured_percent < r.in_sample_fit_vs_measured_percent
        assert r.in_sample_fit_vs_local_percent <= 100.0
    json.dumps(report.to_dict())


def test_leave_one_out_time_domain_vaf() -> None:
    fs = 200.0
    rng = np.random.default_rng(3)
    torque = np.convolve(rng.normal(size=4000), np.ones(20) / 20, mode="same")  # ≲ 10 Hz
    pts = table_points(WIGGLY)
    bt8 = pts[2]
    angle = simulate(*_tf(bt8.parameters), torque, fs)
    pts[2] = OperatingPoint(
        bt8.condition, bt8.mu_N, bt8.parameters, time=TimeData(fs, torque, angle)
    )
    report = leave_one_out(pts, methods=["physical"])
    r = report.get("physical", "BT8")
    assert r.vaf_percent is not None and r.in_sample_vaf_percent is not None
    assert r.vaf_percent < r.in_sample_vaf_percent < 100.0
    assert report.get("physical", "BT12").vaf_percent is None  # no time data there


def _tf(p) -> tuple[np.ndarray, np.ndarray]:
    num = [p["I_i"], p["b_i"] + p["b_c"], p["k_i"] + p["k_c"]]
    den = np.polymul([p["b_c"], p["k_c"]], [p["I_i"], p["b_i"], p["k_i"]])
    return np.array(num), den


def test_simulate_reaches_the_analytic_sine_response() -> None:
    p = {k: v[2] for k, v in WIGGLY.items()}
    fs, f0 = 1000.0, 1.3
    t = np.arange(int(8 * fs)) / fs
    y = simulate(*_tf(p), np.sin(2 * math.pi * f0 * t), fs)
    h = truth(p, np.array([f0]))[0]
    steady = t > 3.0  # transients of the slowest pole (~0.1 s) long gone
    expected = abs(h) * np.sin(2 * math.pi * f0 * t[steady] + np.angle(h))
    np.testing.assert_allclose(y[steady], expected, atol=1e-4 * abs(h))


def test_leave_one_out_needs_enough_points_for_the_order() -> None:
    with pytest.raises(ValueError, match="order 4"):
        leave_one_out(table_points(WIGGLY), order=4)


# (d) FIT% and VAF --------------------------------------------------------------------------


def test_fit_percent_known_values() -> None:
    h = truth({k: v[1] for k, v in WIGGLY.items()}, F_HZ)
    assert fit_percent(h, h, F_HZ) == pytest.approx(100.0)
    c = 1.1 * np.exp(0.1j)  # Ĥ = c·H  ⇒  FIT = 100·(1 − |c − 1|²), whatever the weights
    assert fit_percent(c * h, h, F_HZ) == pytest.approx(100.0 * (1.0 - abs(c - 1.0) ** 2))
    # The 1/f weighting: one error of 0.5 at 4 Hz against |H| = 1 at 1, 2, 4 Hz.
    f = np.array([1.0, 2.0, 4.0])
    got = fit_percent(np.array([1.0, 1.0, 1.5]), np.ones(3), f)
    assert got == pytest.approx(100.0 * (1.0 - 0.25 / 4.0 / (1.0 + 0.5 + 0.25)))


def test_vaf_known_values() -> None:
    th = np.sin(np.linspace(0, 10, 500))
    assert vaf(th, th) == pytest.approx(100.0)
    assert vaf(th, 0.9 * th) == pytest.approx(99.0)
    assert vaf(th, np.zeros_like(th)) == pytest.approx(0.0)
    assert vaf(th, -th) == pytest.approx(-300.0)
    assert vaf(th, -th, clip_at_zero=True) == 0.0


# Table 2 and the RT exclusion --------------------------------------------------------------


def _six_points() -> list[OperatingPoint]:
    pts = table_points(WIGGLY)
    rt = {"I_i": 0.1, "b_i": 1.2, "k_i": 6.0, "b_c": 3.5, "k_c": 60.0}  # different pattern
    pts.append(OperatingPoint("RT", 61.0, rt))  # grip force like BT18's
    return with_measured_frf(pts, seed=11)


def test_fit_table_excludes_rt_by_default_and_says_why() -> None:
    table = fit_table(_six_points())
    rt = table.row("RT")
    assert not rt.included and rt.exclusion_reason == RT_EXCLUSION_REASON
    assert rt.lpv_fit_percent == {"de_caigny": None, "physical": None}
    assert rt.lti_fit_percent is not None  # the local model still gets its LTI FIT%
    assert table.excluded == {"RT": RT_EXCLUSION_REASON} == dict(DEFAULT_EXCLUSIONS)
    for c in CONDITIONS:
        row = table.row(c)
        assert row.included and 90.0 < row.lti_fit_percent <= 100.0
        assert all(v is not None and v > 80.0 for v in row.lpv_fit_percent.values())
    d = table.to_dict()
    json.dumps(d)
    assert d["excluded"]["RT"] == RT_EXCLUSION_REASON
    assert [r["condition"] for r in d["rows"]][:2] == ["BT18", "RT"]  # sorted by μ


def test_rt_exclusion_can_be_overridden() -> None:
    table = fit_table(_six_points(), exclude={})
    assert table.row("RT").included and table.excluded == {}
    assert table.row("RT").lpv_fit_percent["physical"] is not None


def test_analysis_bundle_and_tuple_inputs() -> None:
    pts = [
        (p.condition, p.mu_N, dict(p.parameters), (p.frf.frequencies_hz, p.frf.response))
        for p in _six_points()
    ]
    result = analyse_lpv(pts, frequencies_hz=F_HZ)
    assert set(result.models) == {"de_caigny", "physical"}
    assert all(isinstance(m, LPVModel) for m in result.models.values())
    assert result.models["physical"].mu_range == (60.0, 210.0)
    d = result.to_dict()
    json.dumps(d)
    assert d["models"]["de_caigny"]["structure"] == "second_order"
    assert d["leave_one_out"]["excluded"] == {"RT": RT_EXCLUSION_REASON}
    exact = analyse_lpv(pts, order=4)  # interpolates all 5; no 4-point fold can hold order 4
    assert exact.leave_one_out is None and "order 4" in exact.leave_one_out_skipped


def test_bad_inputs_are_explained() -> None:
    pts = table_points(WIGGLY)
    with pytest.raises(ValueError, match="unique"):
        PhysicalLPV.fit(pts + [pts[0]])
    with pytest.raises(ValueError, match="order 5"):
        PhysicalLPV.fit(pts, order=5)
    with pytest.raises(KeyError, match="k_c"):
        PhysicalLPV.fit([("X", 1.0, {"I_i": 0.1, "b_i": 1, "k_i": 1, "b_c": 1})])
    with pytest.raises(ValueError, match="unknown LPV method"):
        build_lpv(pts, "spline")


# (e) timing -----------------------------------------------------------------------------------


def test_evaluation_timing_is_reported(capsys: pytest.CaptureFixture[str]) -> None:
    pts = table_points(WIGGLY)
    f30 = np.geomspace(0.1, 20.0, 30)
    lines = []
    for method in ("physical", "de_caigny"):
        model = build_lpv(pts, method)
        for name, call in (
            ("parameters(mu)", lambda m=model: m.parameters(123.4)),
            ("frequency_response(mu, 30 f)", lambda m=model: m.frequency_response(123.4, f30)),
        ):
            n = 2000
            best = math.inf
            for _ in range(3):
                t0 = time.perf_counter()
                for _ in range(n):
                    call()
                best = min(best, (time.perf_counter() - t0) / n)
            lines.append(f"{method:10s} {name:30s} {best * 1e6:6.2f} µs/call")
    with capsys.disabled():
        print("\n" + "\n".join(lines))
