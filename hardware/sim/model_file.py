"""World models as files: ``model.toml``, written by ``steerlab diagnose``, read by
``steerlab simulate --model`` (and by the diagnosis itself, as its baseline).

A model file holds

- ``[baseline.COND]``: the simulated driver's behaviour per condition, a population's typical
  subject (geometric mean over the diagnosed subjects): arm parameters (I_i, b_i, k_i, b_c,
  k_c), grip force mean and SD, remnant SD and corner frequency; with ``n_subjects`` and the
  between-subject spread (``*_cv``) for information.
- ``[mechanisms.NAME]``: every mechanism of :class:`hardware.sim.mechanisms.Mechanisms` that
  is on, with all its parameters (the fitted ones and the defaults it was fitted with);
  ``fitted`` lists the fitted ones, ``se`` and ``ci95`` their standard errors and 95 %
  intervals.

:func:`load_world_model` returns a :class:`ModelWorldConfig`: a ``WorldConfig`` (sensors and
wheel inertia at their defaults, the model's mechanisms) that also carries the per-condition
``baseline``; ``app.simulate`` passes it to ``make_population`` as the nominal behaviour, so the
usual between-subject spread is drawn around the diagnosed values. Conditions the file does not
name keep the simulator's nominal behaviour (``hardware.sim.physiology.NOMINAL``): a protocol
may run more conditions than were diagnosed.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

from steerlab.hardware.sim.mechanisms import Mechanisms
from steerlab.hardware.sim.physiology import NOMINAL, ArmParams, ConditionBehaviour
from steerlab.hardware.sim.world import WorldConfig
from steerlab.protocols.protocol import ProtocolError

FORMAT = "steerlab-world-model"
FORMAT_VERSION = 1

ARM_KEYS = {
    "I_i": "I_i_kgm2",
    "b_i": "b_i_Nms_per_rad",
    "k_i": "k_i_Nm_per_rad",
    "b_c": "b_c_Nms_per_rad",
    "k_c": "k_c_Nm_per_rad",
}
BEHAVIOUR_KEYS = {
    "grip_mean_n": "grip_mean_N",
    "grip_sd_n": "grip_sd_N",
    "remnant_sd_nm": "remnant_sd_Nm",
    "remnant_corner_hz": "remnant_corner_Hz",
}


class ModelFileError(ProtocolError):
    """A model file that cannot be read; the message names the file and the key. (A
    ``ProtocolError``: like a protocol, a configuration file the user passed, so the command
    line reports it as bad input.)"""


@dataclass(frozen=True)
class ModelWorldConfig(WorldConfig):
    """A world configuration plus the per-condition behaviour of the population's typical
    subject (``None``: the simulator's nominal behaviour)."""

    baseline: dict[str, ConditionBehaviour] | None = field(default=None, compare=False)
    source: str = ""


# -- writing ------------------------------------------------------------------------------------
def _value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return repr(float(f"{v:.6g}"))
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, list | tuple):
        return "[" + ", ".join(_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{k} = {_value(x)}" for k, x in v.items()) + " }"
    raise TypeError(f"cannot write {type(v).__name__} to TOML")


def world_model_text(
    baseline: dict[str, dict[str, Any]],
    mechanisms: Mechanisms,
    fitted: dict[str, list[dict[str, Any]]] | None = None,
    header: dict[str, Any] | None = None,
    comments: list[str] | None = None,
) -> str:
    """TOML text of a model. ``baseline``: condition → values keyed as in the file
    (``k_i_Nm_per_rad`` …); ``fitted``: mechanism → rows with ``parameter``, ``value``, ``se``,
    ``ci95`` (from the diagnosis)."""
    lines = [f"# {c}" for c in (comments or [])]
    lines += [f'format = "{FORMAT}"', f"format_version = {FORMAT_VERSION}"]
    for k, v in (header or {}).items():
        lines.append(f"{k} = {_value(v)}")
    for cond, vals in baseline.items():
        lines += ["", f'[baseline."{cond}"]']
        lines += [f"{k} = {_value(v)}" for k, v in vals.items()]
    md = mechanisms.to_dict()
    for name in mechanisms.active():
        lines += ["", f"[mechanisms.{name}]"]
        lines += [f"{k} = {_value(v)}" for k, v in md[name].items()]
        rows = (fitted or {}).get(name, [])
        if rows:
            lines.append(f"fitted = {_value([r['parameter'] for r in rows])}")
            lines.append(f"se = {_value({r['parameter']: r['se'] for r in rows})}")
            lines.append(f"ci95 = {_value({r['parameter']: list(r['ci95']) for r in rows})}")
    return "\n".join(lines) + "\n"


# -- reading ------------------------------------------------------------------------------------
def _number(where: str, d: dict, key: str) -> float:
    if key not in d:
        raise ModelFileError(f"{where}: missing {key!r}")
    v = d[key]
    if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
        raise ModelFileError(f"{where}.{key}: must be a finite number, got {v!r}")
    return float(v)


def read_model_file(path: str | Path) -> dict:
    p = Path(path)
    try:
        data = tomllib.loads(p.read_text(encoding="utf-8"))
    except OSError as e:
        raise ModelFileError(f"{p}: cannot read: {e.strerror or e}") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise ModelFileError(f"{p}: not valid TOML ({e})") from None
    if data.get("format") != FORMAT:
        raise ModelFileError(f"{p}: not a Steerlab world model (format = {FORMAT!r} missing)")
    if int(data.get("format_version", 0)) > FORMAT_VERSION:
        raise ModelFileError(
            f"{p}: format_version {data.get('format_version')} is newer than this Steerlab "
            f"reads ({FORMAT_VERSION})"
        )
    return data


def mechanisms_from_model(data: dict, where: str = "model") -> Mechanisms:
    raw = data.get("mechanisms", {}) or {}
    known = {f.name: f for f in fields(Mechanisms)}
    out: dict[str, dict] = {}
    for name, vals in raw.items():
        if name not in known:
            raise ModelFileError(f"{where}: unknown mechanism {name!r}; known: {sorted(known)}")
        cls = type(getattr(Mechanisms(), name))
        allowed = {f.name for f in fields(cls)}
        params = {k: v for k, v in vals.items() if k in allowed}
        # Settings by name (a family's form: hardware.sim.mechanisms): those whose default is.
        named = {k for k in allowed if isinstance(getattr(cls(), k), str)}
        for k, v in params.items():
            if k in named:
                if not isinstance(v, str):
                    raise ModelFileError(f"{where}: mechanisms.{name}.{k} must be a string")
                continue
            if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
                raise ModelFileError(f"{where}: mechanisms.{name}.{k} must be a finite number")
        out[name] = {k: v if k in named else float(v) for k, v in params.items()}
    try:
        return Mechanisms.from_dict(out)
    except (TypeError, ValueError) as e:
        raise ModelFileError(f"{where}: {e}") from None


def baseline_from_model(data: dict, where: str = "model") -> dict[str, ConditionBehaviour]:
    out: dict[str, ConditionBehaviour] = {}
    for cond, vals in (data.get("baseline", {}) or {}).items():
        w = f"{where}: baseline.{cond}"
        if not isinstance(vals, dict):
            raise ModelFileError(f"{w}: must be a table")
        arm = ArmParams(**{a: _number(w, vals, k) for a, k in ARM_KEYS.items()})
        if min(arm.I_i, arm.b_i, arm.k_i, arm.b_c, arm.k_c) <= 0:
            raise ModelFileError(f"{w}: arm parameters must be > 0")
        kw = {a: _number(w, vals, k) for a, k in BEHAVIOUR_KEYS.items()}
        if kw["remnant_corner_hz"] <= 0 or min(kw["grip_sd_n"], kw["remnant_sd_nm"]) < 0:
            raise ModelFileError(f"{w}: remnant corner must be > 0, SDs ≥ 0")
        out[str(cond)] = ConditionBehaviour(arm, **kw)
    return out


def load_world_model(path: str | Path) -> ModelWorldConfig:
    """The world of a model file (see the module docstring)."""
    p = Path(path)
    data = read_model_file(p)
    mech = mechanisms_from_model(data, str(p))
    baseline = baseline_from_model(data, str(p))
    full = dict(NOMINAL)
    full.update(baseline)
    fs = data.get("fs_hz", 1000.0)
    if isinstance(fs, bool) or not isinstance(fs, int | float) or not fs > 0:
        raise ModelFileError(f"{p}: fs_hz must be a number > 0")
    return ModelWorldConfig(fs_hz=float(fs), mechanisms=mech, baseline=full, source=str(p))
