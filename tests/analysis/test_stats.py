"""Repeated-measures ANOVA and pairwise tests, cross-checked against pingouin (test-only dep)."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pingouin as pg
import pytest

from steerlab.analysis.stats import mauchly, pairwise_tests, prepare_wide, rm_anova

CONDS = ["RT", "BT18", "BT12", "BT8", "BT5", "PT"]
TOL = dict(rtol=1e-6, atol=1e-9)

# pingouin 0.7 calls a pandas API that pandas 3 deprecates; not ours to fix.
pytestmark = pytest.mark.filterwarnings("ignore:The inplace keyword")


def _dataset(kind: str) -> np.ndarray:
    """Seeded subjects × conditions tables with different covariance structures."""
    if kind == "compound_symmetric":
        rng = np.random.default_rng(1)
        subj = rng.normal(0, 20, size=(18, 1))
        return 100 + subj + np.arange(6) * 5.0 + rng.normal(0, 8, size=(18, 6))
    if kind == "null_effect":
        rng = np.random.default_rng(2)
        return 50 + rng.normal(0, 5, size=(12, 6)) + rng.normal(0, 10, size=(12, 1))
    if kind == "violated":
        # Error spread grows 30-fold across conditions, so the variances of the differences
        # are far from equal: Mauchly must reject sphericity.
        rng = np.random.default_rng(3)
        sd = np.array([0.5, 0.5, 1.0, 3.0, 8.0, 15.0])
        return (
            80
            + rng.normal(0, 10, size=(30, 1))
            + np.arange(6) * 2.0
            + rng.normal(size=(30, 6)) * sd
        )
    if kind == "four_levels":
        rng = np.random.default_rng(4)
        return rng.normal(size=(9, 4)) + np.array([0.0, 0.3, 1.0, 0.2])
    raise ValueError(kind)


def _long(x: np.ndarray, conds: list[str]) -> pd.DataFrame:
    rows = [
        (f"s{i:02d}", conds[j], x[i, j])
        for i in range(x.shape[0])
        for j in range(x.shape[1])
        if np.isfinite(x[i, j])
    ]
    return pd.DataFrame(rows, columns=["subject", "condition", "grip"])


def _check_against_pingouin(x: np.ndarray) -> None:
    conds = CONDS[: x.shape[1]]
    df = _long(x, conds)
    ours = rm_anova(df, dv="grip", within="condition", subject="subject")
    ref = pg.rm_anova(
        df,
        dv="grip",
        within="condition",
        subject="subject",
        correction=True,
        detailed=True,
        effsize="np2",
    )
    row = ref.iloc[0]
    np.testing.assert_allclose(ours.F, row["F"], **TOL)
    np.testing.assert_allclose(ours.p, row["p_unc"], **TOL)
    np.testing.assert_allclose(ours.ss_effect, row["SS"], **TOL)
    np.testing.assert_allclose(ours.ss_error, ref.iloc[1]["SS"], **TOL)
    assert (ours.df1, ours.df2) == (row["DF"], ref.iloc[1]["DF"])
    np.testing.assert_allclose(ours.partial_eta_squared, row["np2"], **TOL)
    if x.shape[1] > 2:
        np.testing.assert_allclose(ours.eps_gg, row["eps"], **TOL)
        np.testing.assert_allclose(ours.p_gg, row["p_GG_corr"], **TOL)
        np.testing.assert_allclose(ours.sphericity.W, row["W_spher"], **TOL)
        np.testing.assert_allclose(ours.sphericity.p, row["p_spher"], **TOL)
        assert ours.sphericity.met == bool(row["sphericity"])

    ng2 = pg.rm_anova(df, dv="grip", within="condition", subject="subject", effsize="ng2")
    np.testing.assert_allclose(ours.generalized_eta_squared, ng2.iloc[0]["ng2"], **TOL)

    spher = pg.sphericity(df, dv="grip", within="condition", subject="subject")
    ms = mauchly(prepare_wide(df, dv="grip", within="condition", subject="subject").values)
    np.testing.assert_allclose([ms.W, ms.chi2, ms.p], [spher.W, spher.chi2, spher.pval], **TOL)
    assert ms.df == spher.dof
    np.testing.assert_allclose(
        ours.eps_gg, pg.epsilon(df, dv="grip", within="condition", subject="subject"), **TOL
    )
    np.testing.assert_allclose(
        ours.eps_hf,
        pg.epsilon(df, dv="grip", within="condition", subject="subject", correction="hf"),
        **TOL,
    )

    pw = pairwise_tests(df, dv="grip", within="condition", subject="subject")
    ref_pw = pg.pairwise_tests(
        data=df,
        dv="grip",
        within="condition",
        subject="subject",
        padjust="bonf",
        effsize="hedges",
    )
    assert pw.n_comparisons == len(ref_pw) == len(conds) * (len(conds) - 1) // 2
    complete = prepare_wide(df, dv="grip", within="condition", subject="subject").values
    for _, r in ref_pw.iterrows():
        c = pw.get(r["A"], r["B"])
        np.testing.assert_allclose(c.t, r["T"], **TOL)
        np.testing.assert_allclose(c.df, r["dof"], **TOL)
        np.testing.assert_allclose(c.p_unc, r["p_unc"], **TOL)
        np.testing.assert_allclose(c.p_corrected, r["p_corr"], **TOL)
        np.testing.assert_allclose(c.hedges_g, r["hedges"], **TOL)
        ia, ib = conds.index(r["A"]), conds.index(r["B"])
        np.testing.assert_allclose(
            c.mean_difference, np.mean(complete[:, ia] - complete[:, ib]), **TOL
        )


@pytest.mark.parametrize("kind", ["compound_symmetric", "null_effect", "violated", "four_levels"])
def test_matches_pingouin(kind: str) -> None:
    _check_against_pingouin(_dataset(kind))


def test_violated_dataset_really_violates_sphericity() -> None:
    res = rm_anova(_dataset("violated"), conditions=CONDS)
    assert not res.sphericity.met
    assert res.sphericity.p < 0.01
    assert res.eps_gg < 0.5
    assert res.p_gg > res.p  # the correction is conservative


def test_missing_cells_drop_the_subject_and_still_match_pingouin() -> None:
    x = _dataset("compound_symmetric")
    x[2, 3] = np.nan
    x[7, 0] = np.nan
    x[7, 5] = np.nan
    res = rm_anova(x, conditions=CONDS, subjects=[f"s{i:02d}" for i in range(18)])
    assert res.n_subjects == 16
    assert res.dropped_subjects == ["s02", "s07"]
    assert res.to_dict()["n_subjects_dropped"] == 2
    _check_against_pingouin(x)  # long format with those rows absent


def test_array_wide_and_long_inputs_agree() -> None:
    x = _dataset("null_effect")
    a = rm_anova(x, conditions=CONDS)
    b = rm_anova(pd.DataFrame(x, columns=CONDS))
    c = rm_anova(_long(x, CONDS), dv="grip", within="condition", subject="subject")
    for r in (b, c):
        np.testing.assert_allclose(
            [r.F, r.p, r.p_gg, r.sphericity.W], [a.F, a.p, a.p_gg, a.sphericity.W]
        )


def test_repetitions_are_averaged_per_cell() -> None:
    x = _dataset("four_levels")
    conds = CONDS[:4]
    rep1 = _long(x - 1.0, conds)
    rep2 = _long(x + 1.0, conds)
    res = rm_anova(pd.concat([rep1, rep2]), dv="grip", within="condition", subject="subject")
    ref = rm_anova(x, conditions=conds)
    assert res.cells_averaged == x.size
    np.testing.assert_allclose(res.F, ref.F)


def test_condition_order_from_categorical_and_explicit() -> None:
    x = _dataset("four_levels")
    df = _long(x, CONDS[:4])
    order = ["BT8", "RT", "BT12", "BT18"]
    df["condition"] = pd.Categorical(df["condition"], categories=order, ordered=True)
    assert rm_anova(df, dv="grip", within="condition", subject="subject").conditions == order
    pw = pairwise_tests(
        df, dv="grip", within="condition", subject="subject", conditions=["RT", "BT8"]
    )
    assert [(c.a, c.b) for c in pw.comparisons] == [("RT", "BT8")]
    assert pw.comparisons[0].p_corrected == pw.comparisons[0].p_unc  # one comparison


def test_two_conditions_reduce_to_paired_t() -> None:
    x = _dataset("four_levels")[:, :2]
    res = rm_anova(x)
    pw = pairwise_tests(x)
    assert res.eps_gg == 1.0 and res.sphericity.p == 1.0
    np.testing.assert_allclose(res.F, pw.comparisons[0].t ** 2)
    np.testing.assert_allclose(res.p, pw.comparisons[0].p_unc)


def test_results_are_json_ready() -> None:
    df = _long(_dataset("compound_symmetric"), CONDS)
    d = rm_anova(df, dv="grip", within="condition", subject="subject").to_dict()
    p = pairwise_tests(df, dv="grip", within="condition", subject="subject").to_dict()
    json.dumps(d)
    json.dumps(p)
    assert set(d) >= {"F", "df1", "df2", "p", "p_gg", "eps_gg", "partial_eta_squared", "sphericity"}
    assert set(d["sphericity"]) >= {"W", "chi2", "df", "p"}
    assert p["n_comparisons"] == 15


def test_bad_inputs_are_explained() -> None:
    with pytest.raises(ValueError, match="2-D"):
        rm_anova(np.zeros(5))
    with pytest.raises(ValueError, match="complete"):
        rm_anova(np.array([[1.0, np.nan], [2.0, 3.0]]))
    with pytest.raises(ValueError, match="column"):
        rm_anova(pd.DataFrame({"a": [1]}), dv="grip", within="c", subject="s")


def test_two_subjects_do_not_crash_the_huynh_feldt_correction():
    from steerlab.analysis.stats import epsilon_hf, rm_anova

    data = np.array([[1.0, 2.0, 3.5, 4.0], [1.5, 2.5, 3.0, 5.0]])
    assert epsilon_hf(data) == 1.0
    res = rm_anova(data)
    assert np.isfinite(res.F)


def test_mauchly_with_too_few_subjects_is_not_assumed_met():
    # 2 subjects × 3 conditions: the χ² correction factor is 0, the test is undefined. It must
    # not crash (a small imported study still gets its report) and must not assume sphericity.
    from steerlab.analysis.stats import mauchly

    s = mauchly(np.array([[1.0, 2.0, 3.5], [1.2, 2.5, 3.0]]))
    assert np.isnan(s.p) and not s.met
