"""What the runners share: where the PCAN-Basic stand-in, the clients' local copies and the
outputs are, and starting the simulated drive (``run_sim.py``) in a process of its own.

Nothing here is the clients' code: that is fetched by ``fetch.sh`` into the clients folder
(``--clients DIR``, else ``$STEERLAB_SENSODRIVE_CLIENTS``, else ``<repo>/sensodrive-clients``)
and never committed.
"""

from __future__ import annotations

import argparse
import importlib
import os
import subprocess
import sys
from pathlib import Path
from types import ModuleType

HERE = Path(__file__).resolve().parent
REPO = HERE.parents[1]
STANDIN = HERE.parent / "pcanbasic_standin"
CLIENTS_ENV = "STEERLAB_SENSODRIVE_CLIENTS"
DEFAULT_CLIENTS = REPO / "sensodrive-clients"


def add_paths(ap: argparse.ArgumentParser) -> None:
    ap.add_argument(
        "--clients",
        type=Path,
        default=None,
        help=f"the clients' local copies, as fetch.sh lays them out (default ${CLIENTS_ENV}, "
        f"else {DEFAULT_CLIENTS})",
    )
    ap.add_argument(
        "--out", type=Path, default=None, help="where the outputs go (default CLIENTS/results)"
    )


def resolve_paths(args: argparse.Namespace, *client_files: str) -> tuple[Path, Path]:
    """(clients folder, output folder), both absolute. Stops with a pointer to fetch.sh when
    one of ``client_files`` (relative to the clients folder) is missing; otherwise creates the
    output folder."""
    clients = (args.clients or Path(os.environ.get(CLIENTS_ENV) or DEFAULT_CLIENTS)).resolve()
    missing = [str(clients / f) for f in client_files if not (clients / f).is_file()]
    if missing:
        sys.exit(
            "missing: "
            + ", ".join(missing)
            + f"\nfetch the clients first: {HERE / 'fetch.sh'} DIR (and pass --clients DIR)"
        )
    out = (args.out or clients / "results").resolve()
    out.mkdir(parents=True, exist_ok=True)
    return clients, out


def use_standin(channel: str) -> ModuleType:
    """Point the stand-in at a fresh udp_loopback channel, put its directory first on
    ``sys.path`` (for a client's ``from PCANBasic import *``) and import it."""
    os.environ["STEERLAB_PCAN_INTERFACE"] = "udp_loopback"
    os.environ["STEERLAB_PCAN_CHANNEL"] = channel
    sys.path.insert(0, str(STANDIN))
    return importlib.import_module("PCANBasic")


def start_sim(
    channel: str, out_prefix: Path, extra: list[str], env: dict[str, str] | None = None
) -> subprocess.Popen[str]:
    """run_sim.py on ``channel``, writing ``<out_prefix>-frames.csv`` and ``-status.json``
    when its stdin is closed; returns once the node is up."""
    sim = subprocess.Popen(
        [sys.executable, str(HERE / "run_sim.py"), channel, str(out_prefix), *extra],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
        env=env,
    )
    assert sim.stdout is not None
    assert sim.stdout.readline().strip() == "ready"
    return sim


def stop_sim(sim: subprocess.Popen[str]) -> None:
    """Close the node's stdin (it then writes its files) and print its last line."""
    assert sim.stdin is not None and sim.stdout is not None
    sim.stdin.close()
    print(sim.stdout.read().strip())
    sim.wait(10)
