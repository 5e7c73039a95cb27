"""Live window (pyqtgraph + PySide6): traces, progress and the experiment family's result
while a run acquires. The result itself is the family's own analysis
(`feedbench.engine.incremental.LiveAnalysis`) drawn from its `views.panels`.

This package's own module body needs no Qt: `display_problem` tells, before Qt is loaded,
what would make Qt abort the process (no display, a system library of its xcb plugin
missing), so `feedbench live` can say it in one line.
"""

from __future__ import annotations

import ctypes
import os
from typing import Callable, Mapping

XCB_LIBRARIES = {
    "libxcb-cursor.so.0": "libxcb-cursor0", "libxcb-icccm.so.4": "libxcb-icccm4",
    "libxcb-image.so.0": "libxcb-image0", "libxcb-keysyms.so.1": "libxcb-keysyms1",
    "libxcb-render-util.so.0": "libxcb-render-util0", "libxcb-util.so.1": "libxcb-util1",
    "libxkbcommon-x11.so.0": "libxkbcommon-x11-0", "libxcb-randr.so.0": "libxcb-randr0",
    "libxcb-shape.so.0": "libxcb-shape0", "libxcb-xkb.so.1": "libxcb-xkb1",
}
"""Libraries Qt's xcb platform plugin (PySide6's libqxcb.so, libQt6XcbQpa.so.6, by ldd)
loads from the system that a fresh Debian may lack → the Debian package that has them."""


class DisplayError(RuntimeError):
    """The live window cannot open: no display, or Qt's platform plugin cannot load."""


def missing_packages(libraries: Mapping[str, str] = XCB_LIBRARIES,
                     load: Callable[[str], object] = ctypes.CDLL) -> list[str]:
    """The packages of the `libraries` (soname → package) that the loader cannot open."""
    missing = []
    for soname, package in libraries.items():
        try:
            load(soname)
        except OSError:
            missing.append(package)
    return missing


def x_server_error(display: str) -> str:
    """Why an X server at `display` cannot be reached ('' when it can): libxcb's connect."""
    try:
        xcb = ctypes.CDLL("libxcb.so.1")
    except OSError:
        return "libxcb.so.1 not found (apt-get install libxcb1)"
    xcb.xcb_connect.restype = ctypes.c_void_p
    xcb.xcb_connection_has_error.argtypes = xcb.xcb_disconnect.argtypes = [ctypes.c_void_p]
    connection = xcb.xcb_connect(display.encode(), None)
    failed = xcb.xcb_connection_has_error(connection)
    xcb.xcb_disconnect(connection)
    return f"cannot connect to the X display {display}" if failed else ""


def display_problem(environ: Mapping[str, str] = os.environ) -> str:
    """What keeps Qt from opening a window, in one line ('' when nothing does).

    Qt aborts the process when its platform plugin cannot load; this asks first. Only the
    xcb plugin (``QT_QPA_PLATFORM`` unset or ``xcb``) is checked; with it unset and no
    ``DISPLAY``, Qt would take Wayland if ``WAYLAND_DISPLAY`` is set.
    """
    platform = environ.get("QT_QPA_PLATFORM", "").split(":")[0]
    if platform not in ("", "xcb"):
        return ""
    display = environ.get("DISPLAY", "")
    if not display:
        if not platform and environ.get("WAYLAND_DISPLAY"):
            return ""
        return ("no display for the live window (DISPLAY is not set): run it on a desktop, "
                "with ssh -X, under xvfb-run, or set QT_QPA_PLATFORM=offscreen")
    missing = missing_packages()
    if missing:
        return (f"Qt's xcb platform plugin cannot load: apt-get install {' '.join(missing)} "
                "(Debian/Ubuntu package names)")
    return x_server_error(display)


def require_display(environ: Mapping[str, str] = os.environ) -> None:
    """Raise `DisplayError` (one line: what to install or set) where Qt would abort."""
    problem = display_problem(environ)
    if problem:
        raise DisplayError(problem)
