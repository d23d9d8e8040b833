"""A hands-off trial on the live path needs no gloves: their watchdog is off for it (the
drive's checks come first in ``RigDevices.health`` and stay on)."""

from __future__ import annotations

import time

from steerlab.app.rigcheck import hands_off_plan
from steerlab.protocols.protocol import load_protocol
from tests.live.conftest import devices, rig_config  # noqa: F401 (fixtures)


def test_glove_watchdog_is_off_for_a_hands_off_trial_only(devices):  # noqa: F811
    plan = hands_off_plan(load_protocol(), 1)
    setup = plan.setup(plan.trials[0])
    assert setup.hands_off
    devices.glove_sim.stop_streaming()
    time.sleep(1.2)  # the fixture's glove timeout is 1 s
    devices.begin_trial(setup)
    assert devices.health() is None
    devices.hands_off = False
    assert "glove stream stopped" in devices.health()
