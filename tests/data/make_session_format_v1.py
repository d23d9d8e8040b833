"""How tests/data/session_format_v1.h5 was made: a session file of the format before
compression and native attributes (float32 samples, HDF5-enum booleans, JSON lists), written by
the session writer of commit 903afbb. Kept as a file, not re-made, so that the test reads what
that writer wrote. To make it again, run this with an interpreter whose ``steerlab`` is that
commit (e.g. ``git worktree add /tmp/v1 903afbb`` and its own venv):

    python tests/data/make_session_format_v1.py tests/data/session_format_v1.h5
"""

import sys
from dataclasses import replace
from pathlib import Path

from steerlab.hardware.sim.physiology import make_population
from steerlab.hardware.sim.rig import simulated_rig
from steerlab.hardware.sim.world import WorldConfig
from steerlab.protocols.datafile import SessionWriter
from steerlab.protocols.engine import SessionEngine
from steerlab.protocols.protocol import parse_protocol
from steerlab.protocols.session import build_plan

sys.path.insert(1, str(Path(__file__).parents[2]))  # after the interpreter's steerlab
from tests.helpers import fast_protocol_text  # noqa: E402

text = fast_protocol_text().replace("loop_rate_hz = 200.0", "loop_rate_hz = 100.0")
proto = parse_protocol(text.replace("period_s = 45.0", "period_s = 15.0"), "old.toml")
plan = build_plan(proto, 2)
plan = replace(plan, trials=plan.trials[:2])
rig = simulated_rig(make_population(2, seed=1)[1], WorldConfig(fs_hz=100.0))
eng = SessionEngine(plan, rig.batch_loop())
w = SessionWriter(
    sys.argv[1],
    chunk_samples=512,
    extra_attributes={"simulated": True, "simulated_subject": {"a": 1}},
)
eng.subscribe(w)
eng.run()
w.close()
