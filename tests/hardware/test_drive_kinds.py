"""Drives by name: a rig file's ``[drive] kind`` chooses the module; a new kind is one module
and one line in ``hardware.drives.DRIVE_KINDS``."""

from __future__ import annotations

import sys
import textwrap
from pathlib import Path

import pytest

from steerlab.hardware import drives
from steerlab.hardware.can import ConfigError
from steerlab.hardware.can.cia402_kind import CiA402RigDrive
from steerlab.hardware.can.sensodrive import SensoDrive
from steerlab.hardware.interfaces import RigDrive
from steerlab.hardware.rig import load_rig
from tests.helpers import fast_protocol_text

ROOT = Path(__file__).resolve().parents[2]
RIGS = ROOT / "hardware" / "rigs"


def test_every_shipped_rig_file_names_a_kind_that_loads():
    kinds = {p.name: load_rig(p).drive.kind for p in sorted(RIGS.glob("*.toml"))}
    assert kinds == {
        "sensodrive-sim.toml": "sensodrive",
        "sensodrive.toml": "sensodrive",
        "simulated.toml": "cia402",
        # the simulated rig with its grip from an LSL stream, a text-line device (hardware.grips)
        "simulated-lsl-grip.toml": "cia402",
        "simulated-text-grip.toml": "cia402",
    }


def test_a_rig_file_without_a_kind_is_a_cia402_drive(tmp_path):
    text = (RIGS / "simulated.toml").read_text()
    assert "kind" not in text.split("[drive.torque_sensor]")[0]
    assert load_rig(RIGS / "simulated.toml").drive.kind == drives.DEFAULT_KIND == "cia402"


def test_an_unknown_kind_names_the_file_table_and_field(tmp_path):
    path = tmp_path / "rig.toml"
    path.write_text(
        (RIGS / "sensodrive-sim.toml").read_text().replace('"sensodrive"', '"senso"', 1)
    )
    with pytest.raises(ConfigError) as e:
        load_rig(path)
    assert (e.value.file, e.value.section, e.value.field) == (str(path), "drive", "kind")
    assert "'senso'" in str(e.value) and "cia402, sensodrive" in str(e.value)


def test_each_kinds_driver_is_a_rig_drive():
    for cls in (CiA402RigDrive, SensoDrive):
        missing = [
            name
            for name in ("set_wheel", "problem", "status", "drop_bus", "close", "sync", "read")
            if not callable(getattr(cls, name, None))
        ]
        assert not missing, (cls, missing)
        assert isinstance(cls.renders_wheel, bool)
    assert CiA402RigDrive.renders_wheel is False and SensoDrive.renders_wheel is True
    assert RigDrive  # the protocol the live path types them with


TOY_KIND = '''
"""A toy drive kind: a wheel that stays where it is, to show what a kind module holds."""
from dataclasses import dataclass
from typing import ClassVar

from steerlab.hardware.can.config import SafetyConfig, _known, _table
from steerlab.hardware.interfaces import DriveReading


@dataclass(frozen=True)
class ToyConfig:
    kind: ClassVar[str] = "toy"
    interface: str
    channel: str
    safety: SafetyConfig
    bitrate: int = 1_000_000
    loop_rate_hz: float = 1000.0
    sign: int = 1
    source: str = "<toy>"
    angle_quantum_rad: float = 1e-4

    @property
    def torque_sensor(self):
        return type("Sensor", (), {"source": "toy"})()

    def describe(self):
        return {"drive_kind": self.kind}


class ToyDrive:
    renders_wheel = False
    angle_quantum_rad = 1e-4

    def __init__(self, config):
        self.config, self.enabled, self.torque = config, False, 0.0
        self.torque_sensor = ToySensor()

    def enable(self): self.enabled = True
    def disable(self): self.enabled, self.torque = False, 0.0
    def quick_stop(self): self.disable()
    def set_torque(self, nm): self.torque = nm
    def sync(self): pass
    def read(self): return DriveReading(0.0, 0.0, self.torque)
    def set_wheel(self, k, b): pass
    def problem(self): return None
    def status(self): return {"drive_state": "toy", "drive_ok": True,
                              "drive_enabled": self.enabled, "faults": []}
    def drop_bus(self): pass
    def close(self): self.disable()


class ToySensor:
    def read(self): return 0.0
    def zero(self): pass
    def clear_recent(self): pass


class ToyNode:
    faults = ()
    def start(self): pass
    def close(self): pass
    def inject(self, fault): raise ValueError(fault)
    def status(self): return {"applied_torque_nm": 0.0, "zero_torque_since": 0.0,
                              "state": "toy", "enabled_cycles": 0, "errors": []}


class _Kind:
    name = "toy"

    def config(self, document, source):
        drive = {k: v for k, v in _table(document, "drive", source, required=True).items()
                 if k != "kind"}
        safety = SafetyConfig(**_known(_table(document, "safety", source, required=True),
                                       SafetyConfig, source, "safety"))
        return ToyConfig(**drive, safety=safety, source=source)

    def open(self, config):
        return ToyDrive(config)

    def simulate(self, config, plant, open_bus, simulation=None):
        return ToyNode()


KIND = _Kind()
'''


def test_a_new_kind_is_one_module_and_one_line(tmp_path, monkeypatch):
    """The toy kind's module, and its line in DRIVE_KINDS: a simulated rig file naming it runs
    a trial through the same RigDevices and DeviceLoop as every other kind."""
    from steerlab.hardware.live import RigDevices
    from steerlab.protocols.engine import LoopControl
    from steerlab.protocols.protocol import parse_protocol
    from steerlab.protocols.session import build_plan

    (tmp_path / "toy_kind.py").write_text(textwrap.dedent(TOY_KIND))
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setitem(drives.DRIVE_KINDS, "toy", "toy_kind:KIND")  # the one line
    text = (RIGS / "simulated.toml").read_text()
    drive = text[text.index("[drive]") : text.index("[safety]")]
    rig_file = tmp_path / "toy.toml"
    rig_file.write_text(
        text.replace(drive, '[drive]\nkind = "toy"\ninterface = "virtual"\nchannel = "toy"\n\n')
    )
    rig = load_rig(rig_file)
    assert rig.drive.kind == "toy" and rig.describe()["drive_kind"] == "toy"
    devices = RigDevices(rig, subject_number=1)
    try:
        text = fast_protocol_text(loop_rate_hz=1000.0, run_in_s=1.0)
        plan = build_plan(parse_protocol(text, "short.toml"), 1)
        loop = devices.device_loop(realtime=False)
        blocks = list(loop.run_trial(plan.setup(plan.trials[0]), LoopControl()))
        n = sum(len(b["time_s"]) for b in blocks)
        assert n == plan.setup(plan.trials[0]).n_samples
        assert not devices.drive.enabled  # the loop's finalizer disabled it
    finally:
        devices.close()
        sys.modules.pop("toy_kind", None)
