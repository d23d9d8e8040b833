"""The engine, the devices and the analysis know nothing of Qt (docs/style.md: model/view)."""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = ("steerlab.hardware", "steerlab.protocols", "steerlab.analysis")
QT = ("PySide6", "PySide2", "PyQt5", "PyQt6", "shiboken6", "pyqtgraph", "qtpy", "steerlab.app.gui")


def _imports(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out.add(node.module)
        elif isinstance(node, ast.Call) and getattr(node.func, "attr", "") == "import_module":
            if node.args and isinstance(node.args[0], ast.Constant):
                out.add(str(node.args[0].value))
    return out


def _is_qt(name: str) -> bool:
    return any(name == q or name.startswith(q + ".") for q in QT)


@pytest.mark.parametrize("package", PACKAGES)
def test_no_source_file_imports_qt(package):
    files = sorted((ROOT / package.removeprefix("steerlab.")).rglob("*.py"))
    assert files
    bad = {str(f.relative_to(ROOT)): sorted(i for i in _imports(f) if _is_qt(i)) for f in files}
    assert {k: v for k, v in bad.items() if v} == {}


def test_importing_every_module_loads_no_qt():
    code = f"""
import importlib, json, pkgutil, sys
failed = {{}}
for pkg in {PACKAGES!r}:
    mod = importlib.import_module(pkg)
    for info in pkgutil.walk_packages(mod.__path__, pkg + "."):
        try:
            importlib.import_module(info.name)
        except Exception as e:  # reported below; a module mid-edit must not hide the check
            failed[info.name] = repr(e)
qt = sorted(m for m in sys.modules if m.split(".")[0] in {{"PySide6", "PySide2", "PyQt5",
            "PyQt6", "shiboken6", "pyqtgraph", "qtpy"}} or m.startswith("steerlab.app.gui"))
print(json.dumps({{"qt": qt, "failed": failed, "n": len(sys.modules)}}))
"""
    env = {"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin", "MPLBACKEND": ""}
    res = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True,
                         text=True, timeout=120)  # fmt: skip
    assert res.returncode == 0, res.stderr
    out = json.loads(res.stdout.strip().splitlines()[-1])
    assert out["qt"] == [], f"Qt loaded by importing {PACKAGES}: {out['qt']}"
    if out["failed"]:
        import warnings

        warnings.warn(f"modules that did not import (not checked): {out['failed']}", stacklevel=1)


def test_the_scan_sees_qt_imports(tmp_path):
    f = tmp_path / "m.py"
    f.write_text("import os\nfrom PySide6.QtCore import QObject\nimport importlib\n"
                 "importlib.import_module('pyqtgraph')\n")  # fmt: skip
    assert sorted(i for i in _imports(f) if _is_qt(i)) == ["PySide6.QtCore", "pyqtgraph"]
