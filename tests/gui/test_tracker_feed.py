"""The online tracker fed by the engine (the GUI's live admittance panel reads it)."""

from __future__ import annotations

import numpy as np

from steerlab.app.gui.tracker_feed import TrackerFeed
from steerlab.hardware.sim.physiology import make_population
from steerlab.hardware.sim.rig import simulated_rig
from steerlab.hardware.sim.world import WorldConfig
from steerlab.protocols.engine import SessionEngine
from steerlab.protocols.session import build_plan


def _results(path, subject) -> None:
    import json

    pts = [
        {"condition": c, "mu_N": subject.behaviour[c].grip_mean_n,
         "parameters": {k: getattr(subject.behaviour[c].arm, k)
                        for k in ("I_i", "b_i", "k_i", "b_c", "k_c")}}
        for c in ("BT18", "BT12", "BT8", "BT5", "PT")
    ]  # fmt: skip
    path.write_text(json.dumps({"lpv": {"order": 2, "operating_points": pts}}))


def test_feed_tracks_every_block_of_a_trial(fast_protocol, tmp_path):
    subject = make_population(3, seed=5)[2]
    _results(tmp_path / "results.json", subject)
    feed = TrackerFeed()
    feed.set_results(tmp_path / "results.json")
    plan = build_plan(fast_protocol, 3)
    from dataclasses import replace

    plan = replace(plan, trials=plan.trials[1:2])  # one measured trial
    eng = SessionEngine(plan, simulated_rig(subject, WorldConfig(fs_hz=200.0)).batch_loop())
    eng.subscribe(feed)
    eng.run()
    assert feed.error is None, feed.error
    est = feed.estimate
    assert est is not None and est.samples == plan.setup(plan.trials[0]).n_samples
    truth = subject.behaviour[plan.trials[0].condition].arm.k_i
    assert abs(np.log(est.k_i / truth)) < 0.5  # tracks the right order of magnitude


def test_a_broken_calibration_is_reported_not_raised(fast_protocol, tmp_path):
    (tmp_path / "bad.json").write_text("{}")
    feed = TrackerFeed()
    feed.set_results(tmp_path / "bad.json")
    subject = make_population(1, seed=5)[0]
    plan = build_plan(fast_protocol, 1)
    from dataclasses import replace

    eng = SessionEngine(replace(plan, trials=plan.trials[:1]),
                        simulated_rig(subject, WorldConfig(fs_hz=200.0)).batch_loop())  # fmt: skip
    eng.subscribe(feed)
    eng.run()
    assert eng.pending() == []  # the trial completed
    assert feed.error and "online tracker stopped" in feed.error and feed.estimate is None
