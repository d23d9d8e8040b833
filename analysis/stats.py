"""Repeated-measures one-way ANOVA and Bonferroni pairwise tests (docs/method.md, "Statistics").

The design is one within-subject factor (the condition, e.g. RT, BT18, BT12, BT8, BT5, PT) and
one value per subject and condition (e.g. a subject's mean total grip force, or a fitted arm
parameter). Everything is computed with numpy/scipy; pingouin is only a test dependency, used to
cross-check these numbers.

Conventions, chosen to agree with pingouin 0.7 (and so with R's ``mauchly.test``, SPSS, JASP):

- Subjects with any missing cell are dropped from every test (listwise deletion); the results
  say how many and which.
- Several values for one subject and condition (e.g. the two measured repetitions) are averaged
  into one cell before anything else.
- Sphericity: Mauchly's W on the covariance of orthonormal contrasts; its p-value uses the
  second-order (Anderson) approximation as R does, not the plain χ² tail.
- Greenhouse–Geisser ε = (Σλ)² / (d Σλ²) of that covariance, capped at 1; Huynh–Feldt ε is
  the original Huynh & Feldt (1976) formula, capped at 1.
- Pairwise tests are paired t-tests on every pair of conditions, in condition order (A before
  B), with the mean difference A − B; Bonferroni multiplies p by the number of pairs (max 1).
  Hedges g is Cohen's d_av (mean difference over the root mean of the two variances) times
  1 − 3 / (8n − 9), as pingouin computes it for paired samples.
"""

from __future__ import annotations

from collections.abc import Hashable, Sequence
from dataclasses import dataclass, field
from itertools import combinations
from typing import Any

import numpy as np
import pandas as pd
from scipy import stats as sps


@dataclass(frozen=True)
class WideTable:
    """Subjects × conditions, complete cases only, ready for the tests."""

    values: np.ndarray  # (n_subjects, n_conditions)
    subjects: list[Hashable]
    conditions: list[Hashable]
    dropped_subjects: list[Hashable] = field(default_factory=list)
    cells_averaged: int = 0  # cells that held more than one value and were averaged

    @property
    def n_subjects(self) -> int:
        return self.values.shape[0]


def prepare_wide(
    data: np.ndarray | pd.DataFrame,
    *,
    dv: str | None = None,
    within: str | None = None,
    subject: str | None = None,
    conditions: Sequence[Hashable] | None = None,
    subjects: Sequence[Hashable] | None = None,
) -> WideTable:
    """Bring the data to a complete subjects × conditions table.

    ``data`` is either a 2-D array (rows = subjects, columns = conditions, NaN = missing), a
    wide DataFrame (index = subjects, columns = conditions), or a long DataFrame with the columns
    ``dv``, ``within`` and ``subject``. ``conditions`` selects and orders the conditions; by
    default a long DataFrame keeps the category order of ``within`` if it is categorical and the
    order of first appearance otherwise. ``subjects`` labels the rows of a 2-D array.
    """
    cells_averaged = 0
    if isinstance(data, pd.DataFrame) and dv is not None:
        if within is None or subject is None:
            raise ValueError("a long DataFrame needs dv, within and subject column names")
        for col in (dv, within, subject):
            if col not in data.columns:
                raise ValueError(f"column {col!r} not in data (columns: {list(data.columns)})")
        long = data[[subject, within, dv]]
        if conditions is None:
            col = long[within]
            if isinstance(col.dtype, pd.CategoricalDtype):
                conditions = [c for c in col.cat.categories if (col == c).any()]
            else:
                conditions = list(pd.unique(col))
        counts = long.dropna(subset=[dv]).groupby([subject, within], observed=True)[dv].count()
        cells_averaged = int((counts > 1).sum())
        wide = long.pivot_table(
            index=subject, columns=within, values=dv, aggfunc="mean", dropna=False, observed=True
        )
        wide = wide.reindex(columns=list(conditions))
        subject_labels: list[Hashable] = list(wide.index)
        values = wide.to_numpy(dtype=float)
    elif isinstance(data, pd.DataFrame):
        if conditions is None:
            conditions = list(data.columns)
        values = data.reindex(columns=list(conditions)).to_numpy(dtype=float)
        subject_labels = list(data.index)
    else:
        values = np.asarray(data, dtype=float)
        if values.ndim != 2:
            raise ValueError(
                f"expected a subjects × conditions 2-D array, got shape {values.shape}"
            )
        if conditions is None:
            conditions = list(range(values.shape[1]))
        elif len(conditions) != values.shape[1]:
            raise ValueError(f"{len(conditions)} condition names for {values.shape[1]} columns")
        if subjects is not None and len(subjects) != values.shape[0]:
            raise ValueError(f"{len(subjects)} subject labels for {values.shape[0]} rows")
        subject_labels = list(subjects) if subjects is not None else list(range(values.shape[0]))

    complete = np.all(np.isfinite(values), axis=1)
    kept = values[complete]
    conds = list(conditions)
    if len(conds) < 2:
        raise ValueError(f"need at least two conditions, got {len(conds)}")
    if kept.shape[0] < 2:
        raise ValueError(
            f"need at least two subjects with every condition; {kept.shape[0]} of "
            f"{values.shape[0]} are complete"
        )
    return WideTable(
        values=kept,
        subjects=[s for s, ok in zip(subject_labels, complete, strict=True) if ok],
        conditions=conds,
        dropped_subjects=[s for s, ok in zip(subject_labels, complete, strict=True) if not ok],
        cells_averaged=cells_averaged,
    )


def _orthonormal_contrasts(k: int) -> np.ndarray:
    """(k, k−1) orthonormal columns, all orthogonal to the constant; Helmert, normalised.

    W and ε are invariant to which orthonormal basis of the contrast space is used.
    """
    c = np.zeros((k, k - 1))
    for j in range(1, k):
        c[:j, j - 1] = 1.0
        c[j, j - 1] = -float(j)
        c[:, j - 1] /= np.sqrt(j * (j + 1.0))
    return c


def _contrast_cov(values: np.ndarray) -> np.ndarray:
    c = _orthonormal_contrasts(values.shape[1])
    return c.T @ np.cov(values, rowvar=False, ddof=1) @ c


@dataclass(frozen=True)
class Sphericity:
    """Mauchly's test. With two conditions sphericity holds trivially (W = 1, p = 1)."""

    W: float
    chi2: float
    df: int
    p: float
    alpha: float = 0.05

    @property
    def met(self) -> bool:
        return bool(self.p > self.alpha)

    def to_dict(self) -> dict[str, Any]:
        return {
            "test": "Mauchly",
            "W": self.W,
            "chi2": self.chi2,
            "df": self.df,
            "p": self.p,
            "alpha": self.alpha,
            "sphericity_met": self.met,
        }


def mauchly(values: np.ndarray, alpha: float = 0.05) -> Sphericity:
    """Mauchly's sphericity test on a complete subjects × conditions array."""
    n, k = values.shape
    d = k - 1
    if d <= 1:
        return Sphericity(W=1.0, chi2=0.0, df=0, p=1.0, alpha=alpha)
    m = _contrast_cov(values)
    df_resid = n - 1
    sign, logdet = np.linalg.slogdet(m)
    # With fewer subjects than conditions the contrast covariance is singular: W = 0, p = 0.
    log_w = logdet - d * np.log(np.trace(m) / d) if sign > 0 else -np.inf
    w = float(np.exp(log_w))
    df = d * (d + 1) // 2 - 1
    f = 1.0 - (2 * d**2 + d + 2) / (6.0 * d * df_resid)
    if f <= 0:
        # Too few subjects for the test's χ² approximation (e.g. 2 subjects, 3 conditions):
        # sphericity cannot be tested, so it is not assumed (the GG correction applies).
        return Sphericity(W=w, chi2=float("nan"), df=int(df), p=float("nan"), alpha=alpha)
    chi2 = float(-df_resid * f * log_w)
    # Second-order term of the asymptotic expansion, written as R's mauchly.test writes it
    # (R puts the number of conditions k where Anderson has d); it matters for small n.
    w2 = (
        (d + 2)
        * (d - 1)
        * (d - 2)
        * (2 * d**3 + 6 * d**2 + 3 * k + 2)
        / (288.0 * (df_resid * d * f) ** 2)
    )
    p1 = sps.chi2.sf(chi2, df)
    p2 = sps.chi2.sf(chi2, df + 4)
    p = float(p1 + w2 * (p2 - p1))
    return Sphericity(W=w, chi2=chi2, df=int(df), p=p, alpha=alpha)


def epsilon_gg(values: np.ndarray) -> float:
    """Greenhouse–Geisser ε of a complete subjects × conditions array."""
    k = values.shape[1]
    if k <= 2:
        return 1.0
    m = _contrast_cov(values)
    return float(min(np.trace(m) ** 2 / ((k - 1) * np.trace(m @ m)), 1.0))


def epsilon_hf(values: np.ndarray) -> float:
    """Huynh–Feldt ε (original 1976 formula, capped at 1)."""
    n, k = values.shape
    d = k - 1
    if d <= 1:
        return 1.0
    gg = epsilon_gg(values)
    denominator = d * (n - 1 - d * gg)
    if not denominator > 0:
        # Too few subjects for the Huynh–Feldt correction (e.g. 2): it is undefined, and
        # the upper bound 1 is what every implementation falls back to.
        return 1.0
    return float(min((n * d * gg - 2) / denominator, 1.0))


@dataclass(frozen=True)
class RMAnovaResult:
    """One-way repeated-measures ANOVA over the conditions."""

    dv: str | None
    conditions: list[Hashable]
    n_subjects: int
    dropped_subjects: list[Hashable]
    cells_averaged: int
    condition_means: np.ndarray
    condition_sds: np.ndarray
    ss_effect: float
    ss_subjects: float
    ss_error: float
    df1: int
    df2: int
    F: float
    p: float
    eps_gg: float
    eps_hf: float
    p_gg: float
    partial_eta_squared: float
    generalized_eta_squared: float
    sphericity: Sphericity

    @property
    def ms_effect(self) -> float:
        return self.ss_effect / self.df1

    @property
    def ms_error(self) -> float:
        return self.ss_error / self.df2

    @property
    def n_dropped(self) -> int:
        return len(self.dropped_subjects)

    def to_dict(self) -> dict[str, Any]:
        return {
            "test": "one-way repeated-measures ANOVA",
            "dv": self.dv,
            "conditions": [_jsonable(c) for c in self.conditions],
            "n_subjects": self.n_subjects,
            "n_subjects_dropped": self.n_dropped,
            "dropped_subjects": [_jsonable(s) for s in self.dropped_subjects],
            "cells_averaged": self.cells_averaged,
            "condition_means": {
                str(c): float(m) for c, m in zip(self.conditions, self.condition_means, strict=True)
            },
            "condition_sds": {
                str(c): float(s) for c, s in zip(self.conditions, self.condition_sds, strict=True)
            },
            "ss_effect": self.ss_effect,
            "ss_subjects": self.ss_subjects,
            "ss_error": self.ss_error,
            "ms_effect": self.ms_effect,
            "ms_error": self.ms_error,
            "df1": self.df1,
            "df2": self.df2,
            "F": self.F,
            "p": self.p,
            "eps_gg": self.eps_gg,
            "eps_hf": self.eps_hf,
            "df1_gg": self.eps_gg * self.df1,
            "df2_gg": self.eps_gg * self.df2,
            "p_gg": self.p_gg,
            "partial_eta_squared": self.partial_eta_squared,
            "generalized_eta_squared": self.generalized_eta_squared,
            "sphericity": self.sphericity.to_dict(),
        }


def rm_anova(
    data: np.ndarray | pd.DataFrame,
    *,
    dv: str | None = None,
    within: str | None = None,
    subject: str | None = None,
    conditions: Sequence[Hashable] | None = None,
    subjects: Sequence[Hashable] | None = None,
    alpha: float = 0.05,
) -> RMAnovaResult:
    """Repeated-measures one-way ANOVA; see :func:`prepare_wide` for the accepted data forms."""
    table = prepare_wide(
        data, dv=dv, within=within, subject=subject, conditions=conditions, subjects=subjects
    )
    x = table.values
    n, k = x.shape
    grand = x.mean()
    ss_effect = float(n * np.sum((x.mean(axis=0) - grand) ** 2))
    ss_subjects = float(k * np.sum((x.mean(axis=1) - grand) ** 2))
    ss_total = float(np.sum((x - grand) ** 2))
    ss_error = ss_total - ss_effect - ss_subjects
    df1, df2 = k - 1, (k - 1) * (n - 1)
    f_value = (ss_effect / df1) / (ss_error / df2)
    p = float(sps.f.sf(f_value, df1, df2))
    eps = epsilon_gg(x)
    p_gg = float(sps.f.sf(f_value, eps * df1, eps * df2))
    return RMAnovaResult(
        dv=dv,
        conditions=table.conditions,
        n_subjects=n,
        dropped_subjects=table.dropped_subjects,
        cells_averaged=table.cells_averaged,
        condition_means=x.mean(axis=0),
        condition_sds=x.std(axis=0, ddof=1),
        ss_effect=ss_effect,
        ss_subjects=ss_subjects,
        ss_error=ss_error,
        df1=df1,
        df2=df2,
        F=float(f_value),
        p=p,
        eps_gg=eps,
        eps_hf=epsilon_hf(x),
        p_gg=p_gg,
        partial_eta_squared=ss_effect / (ss_effect + ss_error),
        generalized_eta_squared=ss_effect / (ss_effect + ss_subjects + ss_error),
        sphericity=mauchly(x, alpha=alpha),
    )


@dataclass(frozen=True)
class PairwiseComparison:
    a: Hashable
    b: Hashable
    mean_difference: float  # mean over subjects of (a − b), in the units of the dv
    t: float
    df: int
    p_unc: float
    p_corrected: float  # Bonferroni
    hedges_g: float | None

    def to_dict(self) -> dict[str, Any]:
        return {
            "a": _jsonable(self.a),
            "b": _jsonable(self.b),
            "mean_difference_a_minus_b": self.mean_difference,
            "t": self.t,
            "df": self.df,
            "p_unc": self.p_unc,
            "p_bonferroni": self.p_corrected,
            "hedges_g": self.hedges_g,
        }


@dataclass(frozen=True)
class PairwiseResult:
    dv: str | None
    conditions: list[Hashable]
    n_subjects: int
    dropped_subjects: list[Hashable]
    comparisons: list[PairwiseComparison]
    alpha: float = 0.05

    @property
    def n_comparisons(self) -> int:
        return len(self.comparisons)

    def get(self, a: Hashable, b: Hashable) -> PairwiseComparison:
        """The comparison of ``a`` with ``b`` (sign flipped when stored as b vs a)."""
        for c in self.comparisons:
            if (c.a, c.b) == (a, b):
                return c
            if (c.a, c.b) == (b, a):
                return PairwiseComparison(
                    a=a,
                    b=b,
                    mean_difference=-c.mean_difference,
                    t=-c.t,
                    df=c.df,
                    p_unc=c.p_unc,
                    p_corrected=c.p_corrected,
                    hedges_g=None if c.hedges_g is None else -c.hedges_g,
                )
        raise KeyError(f"no comparison between {a!r} and {b!r}")

    def significant(self) -> list[tuple[Hashable, Hashable]]:
        """Pairs whose Bonferroni-corrected p is below alpha."""
        return [(c.a, c.b) for c in self.comparisons if c.p_corrected < self.alpha]

    def to_dict(self) -> dict[str, Any]:
        return {
            "test": "paired t-tests, Bonferroni-corrected",
            "dv": self.dv,
            "conditions": [_jsonable(c) for c in self.conditions],
            "n_subjects": self.n_subjects,
            "n_subjects_dropped": len(self.dropped_subjects),
            "dropped_subjects": [_jsonable(s) for s in self.dropped_subjects],
            "n_comparisons": self.n_comparisons,
            "alpha": self.alpha,
            "comparisons": [c.to_dict() for c in self.comparisons],
        }


def pairwise_tests(
    data: np.ndarray | pd.DataFrame,
    *,
    dv: str | None = None,
    within: str | None = None,
    subject: str | None = None,
    conditions: Sequence[Hashable] | None = None,
    subjects: Sequence[Hashable] | None = None,
    effect_size: bool = True,
    alpha: float = 0.05,
) -> PairwiseResult:
    """Paired t-tests between every pair of conditions, Bonferroni-corrected.

    The same complete subjects are used for every pair (as the ANOVA uses), so the pairwise
    tests and the omnibus test describe the same people.
    """
    table = prepare_wide(
        data, dv=dv, within=within, subject=subject, conditions=conditions, subjects=subjects
    )
    x = table.values
    n, k = x.shape
    pairs = list(combinations(range(k), 2))
    out = []
    for i, j in pairs:
        diff = x[:, i] - x[:, j]
        mean_diff = float(diff.mean())
        sd = float(diff.std(ddof=1))
        t = mean_diff / (sd / np.sqrt(n)) if sd > 0 else np.copysign(np.inf, mean_diff)
        p_unc = float(2.0 * sps.t.sf(abs(t), n - 1)) if np.isfinite(t) else 0.0
        g = None
        if effect_size:
            pooled = np.sqrt((x[:, i].var(ddof=1) + x[:, j].var(ddof=1)) / 2.0)
            g = float(mean_diff / pooled * (1.0 - 3.0 / (8.0 * n - 9.0)))
        out.append(
            PairwiseComparison(
                a=table.conditions[i],
                b=table.conditions[j],
                mean_difference=mean_diff,
                t=float(t),
                df=n - 1,
                p_unc=p_unc,
                p_corrected=min(p_unc * len(pairs), 1.0),
                hedges_g=g,
            )
        )
    return PairwiseResult(
        dv=dv,
        conditions=table.conditions,
        n_subjects=n,
        dropped_subjects=table.dropped_subjects,
        comparisons=out,
        alpha=alpha,
    )


def _jsonable(x: Any) -> Any:
    """Labels may be numpy scalars (from arrays or pandas); JSON wants Python ones."""
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, (str, int, float, bool)) or x is None:
        return x
    return str(x)
