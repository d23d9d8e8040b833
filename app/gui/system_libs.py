"""Can Qt's X11 platform plugin load here? Checked before any Qt GUI module is imported. Qt-free.

PySide6's wheels bring Qt but not the X11 client libraries its ``xcb`` platform plugin links
against. Without them Qt prints "Could not load the Qt platform plugin "xcb"" with a hint that
names one package (libxcb-cursor0), then aborts the interpreter: the experimenter never learns
what to install. :func:`check_xcb` runs ``ldd`` on the plugin instead, and
:func:`missing_libraries_message` names every missing library and the Debian/Ubuntu package that
holds it, in one ``apt-get install`` line.

The table below was made on a minimal Debian 12 (``debootstrap --variant=minbase bookworm``):
``ldd`` on the plugin, its GL integrations and ``libQt6Widgets`` listed what was missing;
``dpkg -S`` named the packages; with exactly these installed nothing is missing and
``steerlab gui`` opens its windows under Xvfb (docs/gui.md, "System packages").
"""

from __future__ import annotations

import importlib.util
import os
import shutil
import subprocess
import sys
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

#: Shared library (soname) → the Debian 12 / Ubuntu package that holds it.
DEBIAN_PACKAGES: dict[str, str] = {
    "libGL.so.1": "libgl1",
    "libEGL.so.1": "libegl1",
    "libxkbcommon.so.0": "libxkbcommon0",
    "libxkbcommon-x11.so.0": "libxkbcommon-x11-0",
    "libxcb-cursor.so.0": "libxcb-cursor0",
    "libxcb-icccm.so.4": "libxcb-icccm4",
    "libxcb-util.so.1": "libxcb-util1",
    "libxcb-image.so.0": "libxcb-image0",
    "libxcb-keysyms.so.1": "libxcb-keysyms1",
    "libxcb-randr.so.0": "libxcb-randr0",
    "libxcb-render-util.so.0": "libxcb-render-util0",
    "libxcb-shm.so.0": "libxcb-shm0",
    "libxcb-sync.so.1": "libxcb-sync1",
    "libxcb-xfixes.so.0": "libxcb-xfixes0",
    "libxcb-render.so.0": "libxcb-render0",
    "libxcb-shape.so.0": "libxcb-shape0",
    "libxcb-xkb.so.1": "libxcb-xkb1",
    "libxcb-glx.so.0": "libxcb-glx0",
    "libxcb.so.1": "libxcb1",
    "libX11-xcb.so.1": "libx11-xcb1",
    "libX11.so.6": "libx11-6",
    "libglib-2.0.so.0": "libglib2.0-0",
    "libgthread-2.0.so.0": "libglib2.0-0",
    "libfontconfig.so.1": "libfontconfig1",
    "libfreetype.so.6": "libfreetype6",
    "libdbus-1.so.3": "libdbus-1-3",
}

#: Every package of the table: the README's one apt-get line.
ALL_PACKAGES: tuple[str, ...] = tuple(dict.fromkeys(DEBIAN_PACKAGES.values()))


@dataclass(frozen=True)
class XcbCheck:
    plugin: Path | None  # the plugin checked; None: not found (nothing checked)
    missing: tuple[str, ...]  # sonames ldd could not resolve

    @property
    def ok(self) -> bool:
        return not self.missing

    @property
    def packages(self) -> tuple[str, ...]:
        """Debian packages holding the missing libraries (known ones), in table order."""
        known = {DEBIAN_PACKAGES[m] for m in self.missing if m in DEBIAN_PACKAGES}
        return tuple(p for p in ALL_PACKAGES if p in known)

    @property
    def unknown(self) -> tuple[str, ...]:
        """Missing libraries the table does not know."""
        return tuple(m for m in self.missing if m not in DEBIAN_PACKAGES)


def uses_xcb(environ: Mapping[str, str] | None = None, platform: str | None = None) -> bool:
    """Will Qt pick its X11 (xcb) plugin? On Linux unless QT_QPA_PLATFORM names another."""
    env = os.environ if environ is None else environ
    if not (platform or sys.platform).startswith("linux"):
        return False
    chosen = env.get("QT_QPA_PLATFORM", "").strip()
    # "xcb", "xcb:…" (plugin options) or a fallback list "wayland;xcb": only the first counts.
    first = chosen.split(";")[0].split(":")[0].strip()
    return first in ("", "xcb")


def no_display(environ: Mapping[str, str] | None = None, platform: str | None = None) -> str | None:
    """Why Qt cannot open a window here, or None. On Linux with Qt's default (X11) platform
    and neither ``DISPLAY`` nor ``WAYLAND_DISPLAY`` set (an ssh login, a service), Qt itself
    would abort the interpreter with a hint about ``libxcb-cursor0``, which is beside the
    point."""
    env = os.environ if environ is None else environ
    if not uses_xcb(env, platform) or env.get("DISPLAY") or env.get("WAYLAND_DISPLAY"):
        return None
    return (
        "no display (DISPLAY and WAYLAND_DISPLAY are unset); run it on a desktop session, "
        "or set QT_QPA_PLATFORM=offscreen for a headless check"
    )


def plugin_path(platform: str = "xcb") -> Path | None:
    """PySide6's platform plugin ``libq<platform>.so``, found without importing Qt's GUI
    modules."""
    spec = importlib.util.find_spec("PySide6")
    if spec is None or not spec.submodule_search_locations:
        return None
    for root in spec.submodule_search_locations:
        p = Path(root) / "Qt" / "plugins" / "platforms" / f"libq{platform}.so"
        if p.is_file():
            return p
    return None


def unresolved_libraries(ldd_output: str) -> tuple[str, ...]:
    """Sonames ``ldd`` reports as "not found", each once, in its order."""
    out = []
    for line in ldd_output.splitlines():
        if "=> not found" in line:
            name = line.split("=>")[0].strip()
            if name and name not in out:
                out.append(name)
    return tuple(out)


def check_xcb(
    plugin: Path | None = None, ldd: str | None = None, platform: str = "xcb"
) -> XcbCheck:
    """``ldd`` the platform plugin (xcb unless told). Without the plugin or without ``ldd``
    nothing can be said: the check passes and Qt reports for itself."""
    plugin = plugin or plugin_path(platform)
    ldd = ldd or shutil.which("ldd")
    if plugin is None or ldd is None:
        return XcbCheck(plugin, ())
    try:
        r = subprocess.run(
            [ldd, str(plugin)], capture_output=True, text=True, timeout=20, check=False
        )
    except (OSError, subprocess.SubprocessError):
        return XcbCheck(plugin, ())
    return XcbCheck(plugin, unresolved_libraries(r.stdout + r.stderr))


def missing_libraries_message(check: XcbCheck) -> str:
    """What the experimenter reads when the xcb plugin cannot load, and what to do."""
    lines = [
        "the GUI cannot start: Qt's X11 platform plugin needs system libraries that are not "
        f"installed: {', '.join(check.missing)} (checked with ldd on {check.plugin}).",
    ]
    if check.packages:
        lines.append(
            "On Debian or Ubuntu install them with:\n"
            f"    sudo apt-get install {' '.join(check.packages)}"
        )
    if check.unknown:
        lines.append(
            "Install the package that provides "
            f"{', '.join(check.unknown)} (Debian: apt-file search NAME)."
        )
    lines.append(
        "Everything the GUI needs on a plain Debian 12, in one line: "
        f"sudo apt-get install {' '.join(ALL_PACKAGES)}"
    )
    return "\n".join(lines)
