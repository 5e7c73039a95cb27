"""What some tests need from the machine, and how its absence is reported.

Outside CI a missing prerequisite skips the test (a developer's laptop may lack Chromium or
the shared data). In CI (`CI=true`, set by `.ci/run`) it fails the test instead: a skip
there would hide a real check.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest

IN_CI = os.environ.get("CI", "").lower() in ("1", "true", "yes")

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
"""Headless Chromium for the report tests (Debian package `chromium`; `.ci/run` installs it)."""


def _shared_data() -> Path:
    """The third-party recordings (EMPS, KUKA, pyFRF impact): `$FEEDBENCH_SHARED_DATA`, else
    `../shared/data` beside the checkout, else the lab machines' `/work/shared/data`."""
    candidates = [Path(os.environ["FEEDBENCH_SHARED_DATA"])] if "FEEDBENCH_SHARED_DATA" in os.environ else []
    candidates += [Path(__file__).resolve().parents[2] / "shared" / "data", Path("/work/shared/data")]
    return next((c for c in candidates if c.is_dir()), candidates[0])


SHARED_DATA = _shared_data()


def requires(available: bool, reason: str) -> pytest.MarkDecorator:
    """Mark a test (or a module, as `pytestmark`) that runs only when `available`."""
    return pytest.mark.requires(available, reason)


def check_requirements(item: pytest.Item) -> None:
    """Skip (or, in CI, fail) an item whose `requires` marks are not met."""
    for mark in item.iter_markers("requires"):
        available, reason = mark.args
        if not available:
            if IN_CI:
                pytest.fail(f"{reason} (CI=true: a missing prerequisite fails instead of skipping)",
                            pytrace=False)
            pytest.skip(reason)
