"""mypy is clean on Steerlab's packages, checked as they are installed (``steerlab.<package>``).

The repository keeps the packages in top-level folders (``app/``, ``protocols/``, ...) that
setup.py maps into ``steerlab``; mypy cannot follow that mapping (nor an editable install's
import hook), so the test builds the installed layout from symbolic links in a temporary
folder and points mypy at it. Settings in pyproject.toml, ``[tool.mypy]``. mypy's default mode
checks the bodies of annotated functions (the public API is annotated).
"""

from __future__ import annotations

import hashlib
import os
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

from tests.helpers import ROOT

PACKAGES = ("steerlab",)  # every subpackage: app (GUI included), analysis, hardware, ...
SUBPACKAGE_FOLDERS = ("app", "analysis", "hardware", "protocols", "benchmarks")


def installed_layout(where: Path) -> Path:
    """``where/steerlab`` as a wheel installs it, from links to the checkout (made anew)."""
    pkg = where / "steerlab"
    if pkg.exists():
        shutil.rmtree(pkg)  # links only: the checkout is not touched
    pkg.mkdir(parents=True)
    for f in (ROOT / "steerlab").iterdir():
        if f.is_file():
            (pkg / f.name).symlink_to(f)
    for folder in SUBPACKAGE_FOLDERS:
        (pkg / folder).symlink_to(ROOT / folder, target_is_directory=True)
    return where


# The slow tier (CI runs it): from a fresh clone mypy has no cache and takes 21 s of the
# everyday tier's six minutes; `pytest -m slow tests/spine/test_types.py` runs it alone.
@pytest.mark.slow
def test_mypy_is_clean():
    pytest.importorskip("mypy", reason="mypy is in the test extra: pip install -e '.[test]'")
    # One place per checkout, kept between runs, so that mypy's cache makes a rerun fast.
    digest = hashlib.sha1(str(ROOT.resolve()).encode()).hexdigest()[:12]
    where = Path(tempfile.gettempdir()) / f"steerlab-mypy-{digest}"
    root = installed_layout(where / "layout")
    args = [sys.executable, "-m", "mypy", "--config-file", str(ROOT / "pyproject.toml")]
    args += ["--cache-dir", str(where / "cache")]
    for p in PACKAGES:
        args += ["-p", p]
    r = subprocess.run(
        args,
        cwd=root,
        env={**os.environ, "MYPYPATH": str(root)},
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert r.returncode == 0, r.stdout[-6000:] + r.stderr[-2000:]
    m = re.search(r"Success: no issues found in (\d+) source files", r.stdout)
    assert m, r.stdout
    # every package was found (115 modules when the test was written)
    assert int(m.group(1)) >= 100, r.stdout
