"""The wheel the diagnosis simulates: the nominal one (Table 1) or the one a rig check measured.

A rig renders its wheel imperfectly (inertia, friction, an unbalanced wheel, a lagging torque
loop; ``docs/rig-check.md``). Diagnosed against the nominal wheel, those show up as mechanisms
the arm model lacks; diagnosed against the measured wheel, the baseline already has them and
the diagnosis looks for what is left.

Which wheel (``docs/diagnosis.md``, "The wheel"):

1. ``--nominal-wheel``: the nominal wheel, whatever the session files record;
2. ``--rig-model RIG.json``: that rig check's wheel, whatever the session files record;
3. otherwise the measured wheel the session files record (``wheel_used`` "measured", written by
   ``simulate --rig-model``; ``rig_check``, written by ``run --rig-check``), when every file
   records the same one;
4. otherwise the nominal wheel, when no file records a measured one.

Files that record different wheels (or some a measured one and some none) are refused: the
diagnosis simulates one rig, and guessing which would hide the choice.

The measured wheel enters the simulated world exactly as in ``simulate --rig-model``
(:func:`analysis.rigcheck.measured_world`): the world's physical inertia and the rendered
damping and stiffness, and the mechanisms ``coulomb_friction``, ``wheel_imbalance`` and
``actuator_lag``, which join the diagnosis' baseline mechanisms (a candidate of the same name
then re-fits the measured value, as for a model file's mechanisms).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from steerlab.analysis.diagnosis.data import DiagnosisError
from steerlab.analysis.rigcheck import (
    PARAMS,
    RigCheckError,
    load_rig_model,
    measured_world,
    recorded_rig_model,
)
from steerlab.hardware.sim.mechanisms import Mechanisms
from steerlab.hardware.sim.world import WorldConfig
from steerlab.protocols.datafile import SessionFile, session_files
from steerlab.protocols.protocol import VirtualWheel

#: The mechanisms a rig check measures (slots of ``Mechanisms``, set by ``measured_world``).
WHEEL_MECHANISMS = ("coulomb_friction", "wheel_imbalance", "actuator_lag")


@dataclass(frozen=True)
class DiagnosisWheel:
    """The wheel of the diagnosis' simulated world, and where it came from."""

    source: str  # "nominal" or "measured"
    chosen_by: str  # why this one (the option, or what the session files record)
    rendered: VirtualWheel = field(default_factory=VirtualWheel)  # inertia, rendered b and k
    mechanisms: Mechanisms = field(default_factory=Mechanisms)  # WHEEL_MECHANISMS only
    rig_json: str | None = None  # the rig check's rig.json (measured)
    recorded_in: list[str] = field(default_factory=list)  # session files recording it
    values: dict[str, float] = field(default_factory=dict)  # rig.json's six values
    sem: dict[str, float | None] = field(default_factory=dict)

    @property
    def measured(self) -> bool:
        return self.source == "measured"

    def apply(self, base: Mechanisms) -> tuple[Mechanisms, list[str]]:
        """``base`` with the wheel's mechanisms in their slots; notes on what they replace."""
        if not self.measured:
            return base, []
        notes = []
        for name in WHEEL_MECHANISMS:
            old, new = getattr(base, name), getattr(self.mechanisms, name)
            if old.active and old != new:
                notes.append(
                    f"the model file's {name} ({old}) is replaced by the measured wheel's ({new})"
                )
        slots = {n: getattr(self.mechanisms, n) for n in WHEEL_MECHANISMS}
        return replace(base, **slots), notes

    def sentence(self) -> str:
        """One line naming the wheel, for the summary and the report."""
        w = self.rendered
        linear = (
            f"I = {w.inertia_kgm2:.4g} kg·m², b = {w.damping_nms_per_rad:.4g} N·m·s/rad, "
            f"k = {w.stiffness_nm_per_rad:.4g} N·m/rad"
        )
        if not self.measured:
            return f"nominal (Table 1: {linear}; {self.chosen_by})"
        v = self.values
        return (
            f"measured by a rig check ({self.rig_json}; {self.chosen_by}): {linear}, "
            f"F_c = {v['coulomb_Nm']:.4g} N·m, m·g·r = {v['gravity_Nm']:.4g} N·m, "
            f"actuator lag {1e3 * v['delay_s']:.3g} ms"
        )

    def to_dict(self) -> dict[str, Any]:
        w = self.rendered
        return {
            "source": self.source,
            "chosen_by": self.chosen_by,
            "rig_json": self.rig_json,
            "recorded_in": self.recorded_in,
            "inertia_kgm2": w.inertia_kgm2,
            "damping_Nms_per_rad": w.damping_nms_per_rad,
            "stiffness_Nm_per_rad": w.stiffness_nm_per_rad,
            "coulomb_Nm": self.mechanisms.coulomb_friction.torque_nm,
            "gravity_Nm": self.mechanisms.wheel_imbalance.torque_nm,
            "delay_s": self.values.get("delay_s", 0.0),
            "actuator_lag_tau_s": self.mechanisms.actuator_lag.tau_s,
            "sem": self.sem or None,
        }


def nominal_wheel(chosen_by: str) -> DiagnosisWheel:
    return DiagnosisWheel("nominal", chosen_by)


def measured_wheel(
    rig_model: dict, fs_hz: float, chosen_by: str, recorded_in: list[str] | None = None
) -> DiagnosisWheel:
    """The wheel of a checked rig model (:func:`analysis.rigcheck.load_rig_model`) for a world
    running at ``fs_hz`` (the actuator lag is converted to that loop rate)."""
    cfg, wheel = measured_world(rig_model, WorldConfig(fs_hz=fs_hz), VirtualWheel(), fs_hz)
    return DiagnosisWheel(
        "measured",
        chosen_by,
        rendered=wheel,
        mechanisms=cfg.mechanisms,
        rig_json=str(rig_model["_path"]),
        recorded_in=list(recorded_in or []),
        values={k: float(rig_model[k]["value"]) for k in PARAMS},
        sem={k: rig_model[k].get("sem") for k in PARAMS},
    )


@dataclass(frozen=True)
class WheelChoice:
    """Which wheel (``rig_model`` None: the nominal one), before the data's rate is known."""

    rig_model: dict | None
    chosen_by: str
    recorded_in: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

    def wheel(self, fs_hz: float) -> DiagnosisWheel:
        """The wheel for a world running at ``fs_hz`` (the actuator lag is converted to it)."""
        if self.rig_model is None:
            return nominal_wheel(self.chosen_by)
        return measured_wheel(self.rig_model, fs_hz, self.chosen_by, self.recorded_in)


def choose_wheel(
    directory: str | Path, *, rig_model: str | Path | None = None, nominal: bool = False
) -> WheelChoice:
    """The wheel to diagnose the session files in ``directory`` with (module docstring).
    Raises :class:`DiagnosisError` for a missing or malformed rig.json or session record
    (naming the file and the field), and for session files that disagree."""
    if nominal and rig_model is not None:
        raise DiagnosisError("--nominal-wheel and --rig-model exclude each other")
    try:
        if rig_model is not None:  # first: a bad rig.json is refused before anything is read
            model = load_rig_model(rig_model)
        recorded = _recorded(directory)
        if nominal:
            notes = _overridden(recorded, "--nominal-wheel")
            return WheelChoice(None, "--nominal-wheel", [], notes)
        if rig_model is not None:
            notes = _overridden(recorded, "--rig-model", keep=model)
            return WheelChoice(model, "--rig-model", [], notes)
    except RigCheckError as e:
        raise DiagnosisError(str(e)) from None
    kinds = {_key(m) for m in recorded.values()}
    if len(kinds) > 1:
        listing = "; ".join(f"{Path(f).name}: {_label(m)}" for f, m in sorted(recorded.items()))
        raise DiagnosisError(
            f"the session files in {directory} record different wheels ({listing}); the "
            "diagnosis simulates one: choose it with --rig-model RIG.json or --nominal-wheel"
        )
    models = [m for m in recorded.values() if m is not None]
    if not models:
        return WheelChoice(None, "the session files record no measured wheel")
    return WheelChoice(models[0], "recorded in the session files", sorted(recorded))


def _recorded(directory: str | Path) -> dict[str, dict | None]:
    """Session file → the measured wheel it records (None: none, or a nominal one)."""
    out: dict[str, dict | None] = {}
    for p in session_files(directory):
        out[str(p)] = recorded_rig_model(SessionFile(p).attrs, str(p))
    return out


def _key(model: dict | None) -> tuple | None:
    # Two records of the same rig check agree on every value (the path may be spelled
    # differently, e.g. relative in one and absolute in another).
    return None if model is None else tuple(float(model[k]["value"]) for k in PARAMS)


def _label(model: dict | None) -> str:
    return "nominal (no measured wheel)" if model is None else f"measured ({model['_path']})"


def _overridden(
    recorded: dict[str, dict | None], option: str, keep: dict | None = None
) -> list[str]:
    """A note when the option overrides a measured wheel the session files record."""
    others = {m["_path"] for m in recorded.values() if m is not None and _key(m) != _key(keep)}
    if not others:
        return []
    return [
        f"{option} overrides the measured wheel the session files record "
        f"({', '.join(sorted(others))})"
    ]
