"""Short protocols shared by the tests that run a session (tests/live, tests/lsl, tests/xdf)."""

from __future__ import annotations

TWO_CONDITIONS = (("BT12", 12.0), ("PT", 0.0))
THREE_CONDITIONS = (("BT12", 12.0), ("BT8", 8.0), ("PT", 0.0))


def short_protocol(
    name: str,
    *,
    loop_rate_hz: float = 1000.0,
    run_in_s: float = 1.0,
    fade_in_s: float = 0.5,
    fade_out_s: float = 0.5,
    period_s: float = 2.5,
    n_bands: int = 10,
    first_bin: int = 3,
    conditions: tuple[tuple[str, float], ...] = TWO_CONDITIONS,
) -> str:
    """A protocol of one period per trial, no familiarisation and no breaks: a trial lasts
    ``run_in_s + period_s + fade_out_s``."""
    text = f"""
name = "{name}"
loop_rate_hz = {loop_rate_hz!r}
[trial]
periods = 1
run_in_s = {run_in_s!r}
fade_in_s = {fade_in_s!r}
fade_out_s = {fade_out_s!r}
familiarization_trials = 0
repetitions = 1
break_between_trials_s = 0.0
break_between_conditions_s = 0.0
[perturbation]
period_s = {period_s!r}
n_bands = {n_bands}
first_bin = {first_bin}
f_max_hz = 20.0
seed = 1
"""
    for cname, boundary in conditions:
        text += f'[[conditions]]\nname = "{cname}"\nboundary_deg = {boundary!r}\n'
    return text


#: Shorter trials: 1.75 s each (run-in 0.5 s + one 1 s period + fade-out 0.25 s).
SHORT_TRIALS_KW = {"run_in_s": 0.5, "fade_in_s": 0.25, "fade_out_s": 0.25, "period_s": 1.0,
                   "n_bands": 5, "first_bin": 1}  # fmt: skip
