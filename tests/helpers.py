"""Helpers shared by test modules."""

from __future__ import annotations

from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def fast_protocol_text(loop_rate_hz: float = 200.0, run_in_s: float = 2.0, periods: int = 1) -> str:
    """The paper's protocol at a lower loop rate: same design, 5× fewer samples."""
    text = (ROOT / "protocols" / "pronker2017.toml").read_text()
    text = text.replace("loop_rate_hz = 1000.0", f"loop_rate_hz = {loop_rate_hz}")
    text = text.replace("run_in_s = 5.0 ", f"run_in_s = {run_in_s} ")
    text = text.replace("periods = 1 ", f"periods = {periods} ")
    return text


def write_rig(tmp_path: Path, text: str) -> Path:
    """``text`` as ``tmp_path/rig.toml``."""
    p = tmp_path / "rig.toml"
    p.write_text(text)
    return p


def edit(text: str, old: str, new: str) -> str:
    """``text`` with ``old`` replaced; fails if ``old`` is not there (a stale test edit)."""
    assert old in text, old
    return text.replace(old, new)
