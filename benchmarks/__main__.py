"""``python -m benchmarks NAME [ARGS]``: run one benchmark; its last output line is one JSON object.

Each benchmark is a module ``benchmarks/NAME.py`` with ``main(argv: list[str]) -> dict``.
"""

from __future__ import annotations

import importlib
import json
import pkgutil
import sys
from pathlib import Path

from steerlab.benchmarks._lsl_loopback import keep_lsl_on_loopback

# Before any benchmark imports pylsl: its LSL traffic stays on the loopback (docs/lsl.md).
keep_lsl_on_loopback()


def available() -> list[str]:
    here = Path(__file__).parent
    return sorted(m.name for m in pkgutil.iter_modules([str(here)]) if not m.name.startswith("_"))


def run(argv: list[str]) -> int:
    if not argv or argv[0] in ("-h", "--help"):
        print("usage: python -m benchmarks NAME [ARGS]\nbenchmarks: " + ", ".join(available()))
        return 0 if argv else 2
    name, rest = argv[0], argv[1:]
    if name not in available():
        print(f"unknown benchmark {name!r}; available: {', '.join(available())}", file=sys.stderr)
        return 2
    result = importlib.import_module(f"steerlab.benchmarks.{name}").main(rest)
    print(json.dumps({"benchmark": name, **result}))
    return 0


if __name__ == "__main__":
    sys.exit(run(sys.argv[1:]))
