"""Shared fixtures: every test gets its own virtual CAN channel and output directory."""

from __future__ import annotations

import itertools
import os
import uuid

import pytest

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")

_counter = itertools.count()


@pytest.fixture
def can_channel() -> str:
    """A python-can `virtual` channel name no other test uses."""
    return f"fb-test-{os.getpid()}-{next(_counter)}-{uuid.uuid4().hex[:6]}"
