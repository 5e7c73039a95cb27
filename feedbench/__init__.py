"""feedbench: bench driver and data acquisition for machine-tool feed drives.

The scripting API (`feedbench.api`, issue 17) is importable from here::

    with feedbench.open_bench("bench.toml") as bench: ...

Its names (``feedbench.api.__all__``) load on first use (PEP 562), so ``import feedbench``
and the CLI stay light.
"""

from __future__ import annotations

from importlib import import_module
from typing import Any

__version__ = "0.1.0"


def __getattr__(name: str) -> Any:
    api = import_module("feedbench.api") if not name.startswith("__") else None
    if api is None or name not in api.__all__:
        raise AttributeError(f"module 'feedbench' has no attribute {name!r}")
    return getattr(api, name)


def __dir__() -> list[str]:
    return sorted([*globals(), *import_module("feedbench.api").__all__])
