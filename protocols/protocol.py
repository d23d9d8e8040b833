"""The protocol: a TOML file a user edits, read into plain validated data.

Every problem is reported as :class:`ProtocolError` naming the file and the field.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

from steerlab.protocols import driving as drv
from steerlab.protocols.names import UnsafeNameError, check_name
from steerlab.protocols.perturbation import PerturbationSpec

DEFAULT_PROTOCOL = "pronker2017.toml"


class ProtocolError(ValueError):
    """A protocol file that cannot be used; the message names the file and the field."""


@dataclass(frozen=True)
class VirtualWheel:
    """The wheel's virtual dynamics (Table 1 of Pronker et al. 2017)."""

    inertia_kgm2: float = 0.3
    damping_nms_per_rad: float = 2.0
    stiffness_nm_per_rad: float = 4.2


@dataclass(frozen=True)
class Segment:
    """One stretch of a time-varying trial: the task of a stationary condition, for a while."""

    condition: str
    duration_s: float


TRANSITIONS = ("step", "ramp")


@dataclass(frozen=True)
class Condition:
    name: str
    boundary_deg: float  # lines at ±boundary_deg; inf: none; 0: on the centre line
    instructions: str = ""
    # Time-varying conditions only: the task changes within the trial, segment by segment
    # (cycled when the trial outlasts them). boundary_deg is then the first segment's.
    segments: tuple[Segment, ...] = ()
    transition: str = "step"  # "step", or "ramp": linear over transition_s from each change
    transition_s: float = 0.0
    # Driving conditions only (``task = "driving"``, protocols/driving.py): the road is the
    # task; boundary_deg is inf (no lines).
    driving: drv.DrivingCondition | None = None

    @property
    def time_varying(self) -> bool:
        return bool(self.segments)


@dataclass(frozen=True)
class TrialTiming:
    periods: int = 1
    run_in_s: float = 5.0
    fade_in_s: float = 1.0
    fade_out_s: float = 1.0
    familiarization_trials: int = 1
    repetitions: int = 2
    break_between_trials_s: float = 15.0
    break_between_conditions_s: float = 60.0


@dataclass(frozen=True)
class Protocol:
    name: str
    conditions: tuple[Condition, ...]
    trial: TrialTiming = field(default_factory=TrialTiming)
    perturbation: PerturbationSpec = field(default_factory=PerturbationSpec)
    wheel: VirtualWheel = field(default_factory=VirtualWheel)
    loop_rate_hz: float = 1000.0
    description: str = ""
    source_text: str = ""  # the TOML as read, stored with every session
    source_path: str = ""
    vehicle: drv.VehicleSpec = field(default_factory=drv.VehicleSpec)  # driving conditions
    road: drv.RoadSpec = field(default_factory=drv.RoadSpec)

    @property
    def condition_names(self) -> list[str]:
        return [c.name for c in self.conditions]

    @property
    def stationary_condition_names(self) -> list[str]:
        return [c.name for c in self.conditions if not c.time_varying and c.driving is None]

    def condition(self, name: str) -> Condition:
        for c in self.conditions:
            if c.name == name:
                return c
        raise ProtocolError(
            f"{self.source_path or 'protocol'}: unknown condition {name!r}; "
            f"the protocol defines {self.condition_names}"
        )

    @property
    def trial_samples(self) -> int:
        t = self.trial
        secs = t.run_in_s + t.periods * self.perturbation.period_s + t.fade_out_s
        return int(round(secs * self.loop_rate_hz))


_TRIAL_KEYS = {
    "periods": int,
    "run_in_s": float,
    "fade_in_s": float,
    "fade_out_s": float,
    "familiarization_trials": int,
    "repetitions": int,
    "break_between_trials_s": float,
    "break_between_conditions_s": float,
}
_PERT_KEYS = {
    "period_s": float,
    "n_bands": int,
    "first_bin": int,
    "f_max_hz": float,
    "full_power_max_hz": float,
    "reduced_power_ratio": float,
    "sd_nm": float,
    "gap_bins": int,
    "seed": int,
}
_WHEEL_KEYS = {
    "inertia_kgm2": ("inertia_kgm2", float),
    "damping_Nms_per_rad": ("damping_nms_per_rad", float),
    "stiffness_Nm_per_rad": ("stiffness_nm_per_rad", float),
}


def _typed(where: str, key: str, value: Any, kind: type) -> Any:
    if kind is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ProtocolError(f"{where}.{key}: expected a whole number, got {value!r}")
        return value
    if kind is float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ProtocolError(f"{where}.{key}: expected a number, got {value!r}")
        return float(value)
    if not isinstance(value, kind):
        raise ProtocolError(f"{where}.{key}: expected {kind.__name__}, got {value!r}")
    return value


def _section(doc: dict, name: str, keys: dict, file: str) -> dict:
    raw = doc.get(name, {})
    where = f"{file}: [{name}]"
    if not isinstance(raw, dict):
        raise ProtocolError(f"{where}: expected a table, got {raw!r}")
    unknown = set(raw) - set(keys)
    if unknown:
        raise ProtocolError(f"{where}: unknown field(s) {sorted(unknown)}; known: {sorted(keys)}")
    out = {}
    for k, v in raw.items():
        spec = keys[k]
        attr, kind = spec if isinstance(spec, tuple) else (k, spec)
        out[attr] = _typed(where, k, v, kind)
    return out


_CONDITION_KEYS = {
    "name",
    "boundary_deg",
    "instructions",
    "segments",
    "transition",
    "transition_s",
    *drv.CONDITION_KEYS,
}


def _time_varying_condition(
    cond: Condition, raw: dict, stationary: dict[str, Condition], loop_rate_hz: float, where: str
) -> Condition:
    """A condition whose task changes within the trial: validated segments and transition."""
    if "boundary_deg" in raw:
        raise ProtocolError(
            f"{where}.boundary_deg: not allowed with segments; each segment's condition sets the "
            "boundary"
        )
    segs = raw["segments"]
    if not isinstance(segs, list) or len(segs) < 2:
        raise ProtocolError(
            f"{where}.segments: expected a list of at least two "
            '{condition = "...", duration_s = ...} tables'
        )
    out = []
    for j, seg in enumerate(segs):
        w = f"{where}.segments[{j + 1}]"
        if not isinstance(seg, dict):
            raise ProtocolError(f"{w}: expected a table {{condition = ..., duration_s = ...}}")
        unknown = set(seg) - {"condition", "duration_s"}
        if unknown:
            raise ProtocolError(f"{w}: unknown field(s) {sorted(unknown)}")
        name = seg.get("condition")
        if not isinstance(name, str) or name not in stationary:
            raise ProtocolError(
                f"{w}.condition: {name!r} is not a stationary condition of this protocol; "
                f"known: {sorted(stationary)}"
            )
        if "duration_s" not in seg:
            raise ProtocolError(f"{w}.duration_s: required")
        d = _typed(w, "duration_s", seg["duration_s"], float)
        if not (math.isfinite(d) and d * loop_rate_hz >= 1.0 and d <= MAX_TRIAL_S):
            raise ProtocolError(
                f"{w}.duration_s: must be a finite number of at least one sample and at most "
                f"{MAX_TRIAL_S:g} s, got {d}"
            )
        out.append(Segment(name, d))
    transition = raw.get("transition", "step")
    if transition not in TRANSITIONS:
        raise ProtocolError(
            f"{where}.transition: must be one of {list(TRANSITIONS)}, got {transition!r}"
        )
    ts = _typed(where, "transition_s", raw.get("transition_s", 0.0), float)
    if transition == "step" and ts != 0.0:
        raise ProtocolError(
            f'{where}.transition_s: only with transition = "ramp" (a step has none)'
        )
    if transition == "ramp":
        shortest = min(s.duration_s for s in out)
        if not (math.isfinite(ts) and 0.0 < ts <= shortest):
            raise ProtocolError(
                f"{where}.transition_s: a ramp needs 0 < transition_s ≤ the shortest segment "
                f"({shortest} s), got {ts}"
            )
    return Condition(
        cond.name,
        stationary[out[0].condition].boundary_deg,
        cond.instructions,
        segments=tuple(out),
        transition=transition,
        transition_s=ts,
    )


MAX_TRIAL_S = 3600.0  # one trial: run-in + periods + fade-out
MAX_PERIOD_S = 600.0
MAX_BREAK_S = 3600.0
MAX_TRIALS_PER_CONDITION = 100
MAX_BANDS = 1000


def _finite_everywhere(doc: Any, file: str) -> None:
    """Every number in the file is finite, except a boundary's ``inf`` (no lines): nan or inf
    anywhere else is an error naming the field, before any of it is used."""

    def where(path: list) -> str:
        head, rest = path[0], path[1:]
        if (
            isinstance(head, str)
            and head in ("trial", "perturbation", "wheel", "vehicle", "road")
            and rest
        ):
            out, rest = f"[{head}]", rest
        elif head == "conditions" and rest and isinstance(rest[0], int):
            out, rest = f"[[conditions]] #{rest[0] + 1}", rest[1:]
        else:
            out, rest = str(head), rest
        for k in rest:
            out += f"[{k + 1}]" if isinstance(k, int) else f".{k}"
        return out

    def walk(v: Any, path: list) -> None:
        if isinstance(v, float) and not math.isfinite(v):
            key = next((k for k in reversed(path) if isinstance(k, str)), "")
            if key == "boundary_deg" and v == math.inf:
                return
            raise ProtocolError(f"{file}: {where(path)}: must be a finite number, got {v}")
        if isinstance(v, dict):
            for k, x in v.items():
                walk(x, [*path, str(k)])
        elif isinstance(v, list):
            for i, x in enumerate(v):
                walk(x, [*path, i])

    walk(doc, [])


def _at_most(where: str, value: float, limit: float, unit: str = "") -> None:
    if value > limit:
        raise ProtocolError(f"{where}: {value:g}{unit} is more than the {limit:g}{unit} allowed")


def parse_protocol(text: str, file: str = "<protocol>") -> Protocol:
    if "\x00" in text:
        raise ProtocolError(f"{file}: a NUL character (not a text file)")
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise ProtocolError(f"{file}: not valid TOML: {e}") from None
    except RecursionError:
        raise ProtocolError(f"{file}: not valid TOML: nested too deeply") from None
    _finite_everywhere(doc, file)
    known_top = {
        "name",
        "description",
        "loop_rate_hz",
        "trial",
        "perturbation",
        "wheel",
        "conditions",
        "vehicle",
        "road",
    }
    unknown = set(doc) - known_top
    if unknown:
        raise ProtocolError(
            f"{file}: unknown field(s) {sorted(unknown)}; known: {sorted(known_top)}"
        )

    name = doc.get("name", Path(file).stem)
    if not isinstance(name, str) or not name:
        raise ProtocolError(f"{file}: name: expected a non-empty string, got {name!r}")
    loop = doc.get("loop_rate_hz", 1000.0)
    if isinstance(loop, bool) or not isinstance(loop, int | float):
        raise ProtocolError(f"{file}: loop_rate_hz: expected a number, got {loop!r}")
    loop = float(loop)
    if not 100.0 <= loop <= 10000.0:
        raise ProtocolError(f"{file}: loop_rate_hz: must be between 100 and 10000 Hz, got {loop}")

    trial = TrialTiming(**_section(doc, "trial", _TRIAL_KEYS, file))
    w = f"{file}: [trial]"
    if trial.periods < 1:
        raise ProtocolError(f"{w}.periods: must be ≥ 1 whole period, got {trial.periods}")
    for key in (
        "run_in_s",
        "fade_in_s",
        "fade_out_s",
        "break_between_trials_s",
        "break_between_conditions_s",
    ):
        v = getattr(trial, key)
        if not (v >= 0 and math.isfinite(v)):
            raise ProtocolError(f"{w}.{key}: must be a finite number ≥ 0 s, got {v}")
    if trial.fade_in_s > trial.run_in_s:
        raise ProtocolError(
            f"{w}.fade_in_s: the fade-in ({trial.fade_in_s} s) must fit inside the run-in "
            f"({trial.run_in_s} s)"
        )
    if trial.familiarization_trials < 0:
        raise ProtocolError(
            f"{w}.familiarization_trials: must be ≥ 0, got {trial.familiarization_trials}"
        )
    if trial.repetitions < 1:
        raise ProtocolError(f"{w}.repetitions: must be ≥ 1, got {trial.repetitions}")
    _at_most(f"{w}.repetitions", trial.repetitions, MAX_TRIALS_PER_CONDITION)
    _at_most(f"{w}.familiarization_trials", trial.familiarization_trials, MAX_TRIALS_PER_CONDITION)
    for key in ("break_between_trials_s", "break_between_conditions_s"):
        _at_most(f"{w}.{key}", getattr(trial, key), MAX_BREAK_S, " s")

    pert = PerturbationSpec(**_section(doc, "perturbation", _PERT_KEYS, file))
    wp = f"{file}: [perturbation]"
    _at_most(f"{wp}.period_s", pert.period_s, MAX_PERIOD_S, " s")
    _at_most(f"{wp}.n_bands", pert.n_bands, MAX_BANDS)
    for key in ("first_bin", "gap_bins"):
        _at_most(f"{wp}.{key}", getattr(pert, key), 100_000)
    if not 0 <= pert.seed < 2**63:
        raise ProtocolError(f"{wp}.seed: must be a whole number from 0 to 2**63 - 1")
    trial_s = trial.run_in_s + trial.periods * pert.period_s + trial.fade_out_s
    if trial_s > MAX_TRIAL_S:
        raise ProtocolError(
            f"{w}.periods: {trial.periods} period(s) of {pert.period_s:g} s make a trial of "
            f"{trial_s:g} s, more than the {MAX_TRIAL_S:g} s allowed"
        )
    try:
        pert.validate(where=f"{file}: [perturbation]")
    except ValueError as e:
        raise ProtocolError(str(e)) from None
    n = pert.period_s * loop
    if abs(n - round(n)) > 1e-9 * n:
        raise ProtocolError(
            f"{file}: [perturbation].period_s: {pert.period_s} s at loop_rate_hz {loop} is not a "
            "whole number of samples"
        )
    if pert.f_max_hz >= loop / 2:
        raise ProtocolError(
            f"{file}: [perturbation].f_max_hz: {pert.f_max_hz} Hz must be below half the loop rate"
        )

    wheel = VirtualWheel(**_section(doc, "wheel", _WHEEL_KEYS, file))
    for key, value in vars(wheel).items():
        if not value >= 0:
            raise ProtocolError(f"{file}: [wheel].{key}: must be ≥ 0, got {value}")

    raw_conds = doc.get("conditions")
    if not isinstance(raw_conds, list) or not raw_conds:
        raise ProtocolError(f"{file}: [[conditions]]: at least one condition is required")
    conds = []
    for i, c in enumerate(raw_conds):
        where = f"{file}: [[conditions]] #{i + 1}"
        if not isinstance(c, dict):
            raise ProtocolError(f"{where}: expected a table")
        unknown = set(c) - _CONDITION_KEYS
        if unknown:
            raise ProtocolError(f"{where}: unknown field(s) {sorted(unknown)}")
        if "name" not in c or not isinstance(c["name"], str) or not c["name"].strip():
            raise ProtocolError(f"{where}.name: required, a non-empty string")
        try:  # the name becomes part of HDF5 group and file names: no '/', '..', NUL
            check_name(c["name"].strip(), f"{where}.name")
        except UnsafeNameError as e:
            raise ProtocolError(str(e)) from None
        instr = c.get("instructions", "")
        if not isinstance(instr, str):
            raise ProtocolError(f"{where}.instructions: expected a string")
        if "task" in c:
            try:
                dc = drv.parse_condition(c, f"{where} ({c['name'].strip()})")
            except ValueError as e:
                raise ProtocolError(str(e)) from None
            conds.append(Condition(c["name"].strip(), math.inf, instr, driving=dc))
            continue
        for key in drv.CONDITION_KEYS:
            if key in c:
                raise ProtocolError(
                    f'{where} ({c["name"]}).{key}: only for a driving condition (task = "driving")'
                )
        if "segments" in c:
            # Checked once every stationary condition is known (segments may name later ones).
            conds.append(Condition(c["name"].strip(), math.nan, instr))
            continue
        for key in ("transition", "transition_s"):
            if key in c:
                raise ProtocolError(
                    f"{where} ({c['name']}).{key}: only for a time-varying condition "
                    "(one with segments)"
                )
        if "boundary_deg" not in c:
            raise ProtocolError(f"{where} ({c['name']}).boundary_deg: required (inf for none)")
        bd = _typed(where, "boundary_deg", c["boundary_deg"], float)
        if not bd >= 0:
            raise ProtocolError(f"{where} ({c['name']}).boundary_deg: must be ≥ 0 or inf, got {bd}")
        conds.append(Condition(c["name"].strip(), bd, instr))
    stationary = {c.name: c for c in conds if not math.isnan(c.boundary_deg) and c.driving is None}
    for i, (c, raw) in enumerate(zip(conds, raw_conds, strict=True)):
        if "segments" in raw:
            conds[i] = _time_varying_condition(
                c, raw, stationary, loop, f"{file}: [[conditions]] #{i + 1} ({c.name})"
            )
    names = [c.name for c in conds]
    dup = {n for n in names if names.count(n) > 1}
    if dup:
        raise ProtocolError(f"{file}: [[conditions]]: duplicate condition name(s) {sorted(dup)}")

    try:
        vehicle = drv.parse_vehicle(doc.get("vehicle"), file)
        road = drv.parse_road(doc.get("road"), file)
    except ValueError as e:
        raise ProtocolError(str(e)) from None
    return Protocol(
        name=name,
        description=str(doc.get("description", "")),
        conditions=tuple(conds),
        trial=trial,
        perturbation=pert,
        wheel=wheel,
        loop_rate_hz=loop,
        source_text=text,
        source_path=file,
        vehicle=vehicle,
        road=road,
    )


def load_protocol(path: str | Path | None = None) -> Protocol:
    """Read a protocol file; None gives the default (the paper's) protocol. A bare file name
    that does not exist in the working folder names a protocol shipped in ``protocols/``."""
    if path is None:
        default = resources.files("steerlab.protocols").joinpath(DEFAULT_PROTOCOL)
        text = default.read_text(encoding="utf-8")
        return parse_protocol(text, DEFAULT_PROTOCOL)
    p = Path(path)
    if not p.exists() and str(p) == p.name:
        # A bare name that is no file here: one of the protocols shipped with Steerlab
        # (``--protocol driving.toml``, ``--protocol tracking.toml``).
        shipped = resources.files("steerlab.protocols").joinpath(p.name)
        if p.suffix == ".toml" and shipped.is_file():
            return parse_protocol(shipped.read_text(encoding="utf-8"), p.name)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as e:
        raise ProtocolError(f"{p}: cannot read protocol file: {e.strerror or e}") from None
    except UnicodeDecodeError:
        raise ProtocolError(f"{p}: not a text (UTF-8) file") from None
    return parse_protocol(text, str(p))
