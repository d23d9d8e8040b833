"""What the documentation names as a file of the repository exists.

Narrow on purpose: markdown links to relative targets, any ``NAME.md``, and back-quoted paths
that start with a top-level folder of the repository and end in a file extension (no
placeholders such as ``NAME``, ``DIR`` or ``*``). A name is found relative to the page, the
repository root or ``docs/``.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PAGES = sorted((ROOT / "docs").rglob("*.md"))
TOP = ("analysis", "app", "protocols", "hardware", "docs", "tests", "benchmarks")
EXTENSIONS = ("py", "md", "toml", "csv", "json", "h5", "eds", "png", "txt", "html", "R", "m")
LINK = re.compile(r"\]\(([^)\s]+)\)")
QUOTED = re.compile(r"`([^`\s]+)`")
MD_NAME = re.compile(r"(?<![\w/.:-])([\w./-]+\.md)\b")
PLACEHOLDER = re.compile(r"[*<>{}…]|NAME|DIR|\.\.\.")
# Broken references in pages that this test's authors do not maintain; each must still be
# broken (fix the page, then drop the entry).
KNOWN_BROKEN: set[tuple[str, str]] = set()


def _named_files(page: Path) -> set[str]:
    text = page.read_text(encoding="utf-8")
    names = set()
    for m in LINK.finditer(text):
        target = m.group(1).split("#")[0]
        if target and not re.match(r"[a-z][a-z0-9+.-]*:", target):
            names.add(target)
    for m in QUOTED.finditer(text):
        t = m.group(1).rstrip(".,:;")
        top, _, _ = t.partition("/")
        ext = t.rsplit(".", 1)[-1] if "." in t.rsplit("/", 1)[-1] else ""
        if top in TOP and "/" in t and ext in EXTENSIONS and not PLACEHOLDER.search(t):
            names.add(t)
    names.update(m.group(1) for m in MD_NAME.finditer(text) if not PLACEHOLDER.search(m.group(1)))
    return names


def _exists(page: Path, name: str) -> bool:
    return any((base / name).exists() for base in (page.parent, ROOT, ROOT / "docs"))


@pytest.mark.parametrize("page", PAGES, ids=[str(p.relative_to(ROOT)) for p in PAGES])
def test_files_the_docs_name_exist(page):
    rel = str(page.relative_to(ROOT))
    missing = sorted(n for n in _named_files(page) if not _exists(page, n))
    assert [n for n in missing if (rel, n) not in KNOWN_BROKEN] == [], rel
    for known_page, name in KNOWN_BROKEN:
        if known_page == rel:
            assert name in missing, f"{rel}: {name} is fixed: drop it from KNOWN_BROKEN"


def test_the_scan_sees_what_it_should(tmp_path):
    page = tmp_path / "p.md"
    page.write_text(
        "see DEVELOPERS.md, [a](other.md#x), `protocols/interchange.py`, "
        "`benchmarks/otherworld.CONVENTIONS`, `docs/NAME.md`, [web](https://x.org/a.md)"
    )
    assert _named_files(page) == {
        "DEVELOPERS.md",
        "other.md",
        "protocols/interchange.py",
    }
