"""A whole study through analyze_study (analysis.study)."""

import concurrent.futures as cf
import json

import numpy as np
import pytest

from steerlab.analysis.armfit import FitOptions
from steerlab.analysis.periods import select_periods
from steerlab.analysis.study import AnalysisOptions, StudyAnalysis, analyze_study
from steerlab.protocols.records import STATUS_ABORTED, STATUS_INCOMPLETE, STATUS_SUPERSEDED
from tests.analysis.synthetic_trials import ARM, admittance, find_example, load_example, make_trial

CONDITION_ARMS = {
    "BT12": ARM,
    "PT": {"I_i": 0.1, "b_i": 1.0, "k_i": 50.0, "b_c": 4.2, "k_c": 230.0},
}
SUBJECT_SCALE = {"S01": 0.8, "S02": 1.0, "S03": 1.25}


def arm_of(subject, condition):
    a = CONDITION_ARMS[condition]
    k = SUBJECT_SCALE[subject]
    return dict(a, k_i=a["k_i"] * k, k_c=a["k_c"] * k)


def trial(subject, condition, rep, *, index, **kw):
    kw.setdefault("grip_mean", 50.0 + 10 * rep + (100.0 if condition == "PT" else 0.0))
    kw.setdefault("run_in_s", 2.5)
    return make_trial(
        arm_of(subject, condition), fs_hz=200.0, subject=subject,
        condition=condition, repetition=rep, trial_index=index, seed=index, **kw,
    )  # fmt: skip


def study_records():
    recs, index = [], 0
    for s in SUBJECT_SCALE:
        for c in CONDITION_ARMS:
            for rep in (0, 1, 2):
                index += 1
                recs.append(trial(s, c, rep, index=index))
    short = trial("S03", "BT12", 3, index=90, run_in_s=0.0)
    short.measured_stop = short.measured_start + 1000
    extra = [
        trial("S01", "BT12", 3, index=91, status=STATUS_ABORTED, abort_reason="grip lost"),
        trial("S01", "PT", 3, index=92, status=STATUS_INCOMPLETE),
        trial("S02", "PT", 2, index=93, status=STATUS_SUPERSEDED),
        short,
        # A second complete record of S02 BT12 rep 1 recorded earlier: the later one is used.
        trial("S02", "BT12", 1, index=0, grip_mean=999.0),
    ]
    return recs + extra


@pytest.fixture(scope="module")
def records():
    return study_records()


IDEAL = AnalysisOptions(fit=FitOptions(sampling="ideal"))


@pytest.fixture(scope="module")
def study(records):
    # Synthetic trials are the continuous steady state sampled ideally: exact recovery is
    # checked against the continuous model (the default's zero-order-hold term is tested in
    # test_estimator_validity.py).
    return analyze_study(records, options=IDEAL)


def test_unusable_trials_are_listed_with_reasons(study):
    reasons = {s.label: s.reason for s in study.skipped}
    assert sum("familiarization" in r for r in reasons.values()) == 6
    assert reasons["S01_BT12_rep3"] == "aborted: grip lost"
    assert reasons["S01_PT_rep3"].startswith("incomplete")
    assert reasons["S02_PT_rep2"].startswith("superseded")
    assert reasons["S03_BT12_rep3"].startswith("not analysable: synthetic:S03_BT12_rep3")
    dup = [s for s in study.skipped if "duplicate" in s.reason]
    assert len(dup) == 1 and dup[0].source.endswith("seed0")
    assert len(study.skipped) == 11


def test_every_subject_and_condition_is_fitted(study):
    assert len(study.subject_conditions) == 6
    for r in study.subject_conditions:
        assert r.repetitions == (1, 2)
        arm = arm_of(r.subject, r.condition)
        for n in ("I_i", "b_i", "k_i", "b_c", "k_c"):
            assert getattr(r.fit.params, n) == pytest.approx(arm[n], rel=1e-6)
        assert r.vaf_percent > 99.999 and r.fit_percent > 99.999
        np.testing.assert_allclose(
            r.frf.H, np.sum(r.frf.bin_weights * admittance(arm, r.frf.bin_frequencies_hz), 1),
            rtol=1e-9,
        )  # fmt: skip


def test_grip_statistics_pool_the_analysed_samples(study, records):
    r = study.result("S02", "BT12")
    used = [
        rec for rec in records
        if (rec.subject, rec.condition) == ("S02", "BT12") and rec.repetition in (1, 2)
        and rec.trial_index != 0
    ]  # fmt: skip
    samples = np.concatenate([select_periods(rec).segment(rec.grip_force_N) for rec in used])
    assert r.grip_mean_N == pytest.approx(samples.mean())
    assert r.grip_sd_N == pytest.approx(samples.std(ddof=1))
    assert r.grip_mean_N < 100  # the earlier duplicate (grip 999 N) was not used


def test_condition_level_group_frf_fit_and_grip(study):
    assert [c.condition for c in study.conditions] == ["BT12", "PT"]
    for c in study.conditions:
        subj = [study.result(s, c.condition) for s in SUBJECT_SCALE]
        np.testing.assert_allclose(c.group_frf.H, np.mean([r.frf.H for r in subj], axis=0))
        assert c.subjects == tuple(SUBJECT_SCALE)
        assert c.fit is not None and c.fit.fit_percent > 99.0
        assert c.fit.sem_method == "noise"  # from the spread between subjects
        assert c.grip_median_of_means_N == pytest.approx(np.median([r.grip_mean_N for r in subj]))
    points = study.operating_points()
    assert [p[0] for p in points] == ["BT12", "PT"]
    assert points[0][1] < points[1][1]


def test_to_dict_is_strict_json_with_unit_keys(study):
    d = study.to_dict()
    text = json.dumps(d, allow_nan=False)
    assert "k_i_Nm_per_rad" in text and "grip_mean_N" in text
    row = d["subject_condition_table"][0]
    assert {"subject", "condition", "k_i_Nm_per_rad", "sem_k_i_Nm_per_rad", "vaf_percent"} <= set(
        row
    )
    assert len(d["skipped_trials"]) == 11
    assert d["conditions"][0]["group_frf"]["n_subjects"] == 3


def _summary(s: StudyAnalysis):
    d = s.to_dict()
    return json.dumps([d["subject_condition_table"], d["skipped_trials"], d["conditions"]])


def test_executors_give_the_same_results(records, study):
    calls = []
    with cf.ThreadPoolExecutor(max_workers=2) as ex:
        threaded = analyze_study(
            records, executor=ex, progress=lambda *a: calls.append(a), options=IDEAL
        )
    assert _summary(threaded) == _summary(study)
    n_run = 3 * 2 * 2 + 1  # measured repetitions + the short trial, which fails in its worker
    assert len(calls) == n_run and calls[-1][:2] == (n_run, n_run)


def test_process_pool_gives_the_same_results(records, study):
    assert _summary(analyze_study(records, jobs=2, options=IDEAL)) == _summary(study)


def test_a_dask_local_cluster_gives_the_same_results(records, study):
    pytest.importorskip("distributed", reason="Dask is the optional extra steerlab[dask]")
    from steerlab.analysis.executors import executor_for

    with executor_for("local:2") as ex:
        assert ex is not None and type(ex).__module__.startswith("distributed")
        on_dask = analyze_study(records, executor=ex, options=IDEAL)
    assert _summary(on_dask) == _summary(study)


def test_a_bad_scheduler_is_named():
    from steerlab.analysis.executors import SchedulerError, executor_for

    with pytest.raises(SchedulerError, match="local:N"):
        with executor_for("local:zero"):
            pass
    pytest.importorskip("distributed")
    with pytest.raises(SchedulerError, match="no Dask scheduler"):
        with executor_for("tcp://127.0.0.1:9", connect_timeout_s=2):
            pass


def test_shared_example_gives_a_plausible_admittance():
    path = find_example()
    if path is None:
        pytest.skip("shared interchange example not found (set STEERLAB_EXAMPLES)")
    res = analyze_study([load_example(path)], options=AnalysisOptions())
    assert not res.skipped and not res.notes
    r = res.result("S01", "BT12")
    assert r.trials[0].excitation.origin == "detected"
    assert r.trials[0].selection.origin == "end-aligned"
    low = r.frf.magnitude[:3]
    assert np.all((low > 0.06) & (low < 0.10))  # ≈ 0.08 rad/N·m
    assert r.frf.phase_deg[-1] == pytest.approx(-90.0, abs=10.0)
    assert r.frf.frequencies_hz[-1] == pytest.approx(20.0, abs=0.1)
    assert np.median(r.frf.coherence) > 0.9
    assert r.fit.success and r.fit.fit_percent > 95.0 and r.vaf_percent > 90.0
    assert 5.0 < r.fit.params.k_i < 50.0 and 0.5 < r.fit.params.b_c < 10.0
    assert 30.0 < r.grip_mean_N < 60.0
