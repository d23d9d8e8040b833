"""The independent world's side of ``python -m benchmarks diagnose`` (issue 18 item 3).

Studies of :mod:`benchmarks.otherworld` (no code shared with ``hardware/sim``): 2 subjects ×
BT18, BT8, PT, two repetitions, 250 Hz, arm inertia 0.07 kg·m², each form of each mechanism
family at the world's own moderate default (``otherworld.MECHANISMS``), and null studies. A
study reaches the diagnosis only as interchange files through ``steerlab import``; the CSV
directory, which holds ``truth.json``, is deleted first.
"""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any

# The diagnosis' name for each of the world's mechanism kinds.
FAMILY_NAME = {
    "reflex": "reflex_delay",
    "friction": "coulomb_friction",
    "stiffening": "stiffness_nonlinearity",
    "actuator_lag": "actuator_lag",
    "sensor_delay": "sensor_delay",
    "grip_stiffness": "grip_scheduled_stiffness",
    "drift": "drift",
}
STUDY: dict[str, Any] = {"subjects": 2, "conditions": ("BT18", "BT8", "PT"), "fs_hz": 250.0}
# For the tests: one subject, one condition, one period per trial.
SMALL_STUDY: dict[str, Any] = {"subjects": 1, "conditions": ("PT",), "fs_hz": 250.0, "n_periods": 1,
               "run_in_s": (3.0, 6.0)}  # fmt: skip
# --quick: one form per family (the world's HIDDEN set, issue 18's table).
QUICK_FORMS = {
    "reflex": ("position_velocity",),
    "friction": ("coulomb",),
    "stiffening": ("cubic",),
    "actuator_lag": ("first_order",),
    "sensor_delay": ("delay",),
    "grip_stiffness": ("power",),
    "drift": ("linear",),
}


def all_forms() -> dict[str, tuple[str, ...]]:
    from steerlab.benchmarks.otherworld import MECHANISMS

    return {kind: tuple(forms) for kind, forms in MECHANISMS.items()}


def hidden_mechanism(kind: str, form: str) -> dict:
    """The family's moderate magnitude in ``form``: the world's HIDDEN entry where the form
    is the same (the reflex's 35 ms delay, issue 18's table), else the form's defaults."""
    from steerlab.benchmarks.otherworld import HIDDEN, mechanism

    ref = HIDDEN[kind]
    if ref["form"] != form:
        return mechanism(kind, form)
    return mechanism(kind, form, **{k: v for k, v in ref.items() if k not in ("kind", "form")})


def make_study(
    root: Path, kind: str | None, form: str | None, *, seed: int, small: bool = False
) -> Path:
    """Generate, import, delete the CSVs (and the truth with them); return the sessions.
    ``small``: :data:`SMALL_STUDY` instead of :data:`STUDY`."""
    from steerlab.benchmarks.otherworld import generate_study
    from steerlab.protocols.interchange import import_study

    hidden = [] if kind is None or form is None else [hidden_mechanism(kind, form)]
    study = SMALL_STUDY if small else STUDY
    generate_study(root / "csv", seed=seed, mechanisms=hidden, **study)
    import_study(root / "csv", root / "sessions")
    shutil.rmtree(root / "csv")
    return root / "sessions"


def cases(quick: bool, seeds: int, nulls: int, only: list[str] | None) -> list[tuple]:
    forms = QUICK_FORMS if quick else all_forms()
    out: list[tuple] = []
    for kind, fs in forms.items():
        if only and kind not in only and FAMILY_NAME[kind] not in only:
            continue
        for form in fs:
            out += [("otherworld", kind, form, 1000 + 17 * s) for s in range(seeds)]
    out += [("otherworld", None, None, 5000 + s) for s in range(nulls)]
    return out


def summarise(results: list[dict]) -> dict:
    """Per family and form: what was named; overall: correct names, false alarms, time."""
    rows = [r for r in results if r["world"] == "otherworld"]
    per: dict[str, dict] = {}
    for r in rows:
        if r["kind"] is None:
            continue
        fam = per.setdefault(r["kind"], {"expected": FAMILY_NAME[r["kind"]], "forms": {}})
        fam["forms"].setdefault(r["form"], []).append(
            {"cause": r["cause"], "causes": r["causes"], "seed": r["seed"]}
        )
    for fam in per.values():
        named = [c["cause"] == fam["expected"] for f in fam["forms"].values() for c in f]
        fam["correct_name_rate"] = sum(named) / len(named)
    hidden = [r for r in rows if r["kind"] is not None]
    nulls = [r for r in rows if r["kind"] is None]
    correct = sum(r["cause"] == FAMILY_NAME[r["kind"]] for r in hidden)
    return {
        "per_family": per,
        "correct_name_rate_at_moderate": correct / len(hidden) if hidden else None,
        "n_hidden": len(hidden),
        "false_alarm_rate": sum(r["cause"] != "none" for r in nulls) / len(nulls)
        if nulls
        else None,
        "false_alarm_causes": sorted({r["cause"] for r in nulls if r["cause"] != "none"}),
        "n_null": len(nulls),
        "errors": sum(r["cause"] == "error" for r in rows),
        "seconds_per_study": time_summary(rows),
        "study": {
            **STUDY,
            "conditions": list(STUDY["conditions"]),
            "repetitions": 2,
            "arm_inertia_kgm2": 0.07,
        },  # fmt: skip
        "goals": {
            "correct_name_at_moderate_min": 0.9,
            "false_alarm_max": 0.05,
            # Wall seconds of a study diagnosed as steerlab diagnose does it on this machine
            # (a worker per core: ``--jobs 1 --study-jobs <cores>``, the machine otherwise idle).
            "seconds_per_study_max": 60.0,
        },  # fmt: skip
    }


def time_summary(rows: list[dict]) -> dict:
    """Median and largest wall and CPU seconds of the diagnosis (the machine is shared: CPU
    seconds are what compare)."""
    out = {}
    for key in ("seconds", "cpu_seconds"):
        v = sorted(r[key] for r in rows if r.get(key) is not None)
        out[key] = {"median": v[len(v) // 2] if v else None, "max": v[-1] if v else None}
    return out
