"""`feedbench sim` started by a test: the simulated bench in its own process, on free
loopback ports (socketcand and Modbus), as a user starts it."""

from __future__ import annotations

import json
import subprocess
import sys
import uuid
from pathlib import Path

from feedbench.sim_backends.process import READY


def start_sim(directory: Path, prefix: str = "sim", config: Path | None = None,
              options: tuple[str, ...] = ()) -> tuple[subprocess.Popen, dict]:
    """Start `feedbench sim` with a config in `directory` (or `config`, which listens on
    loopback itself) and command-line `options`; its process and its ready info
    (addresses, channel) with ``directory`` added."""
    if config is None:
        config = directory / "bench.toml"
        config.write_text('[bench]\nsimulated = true\ninterface = "socketcand"\n'
                          'socketcand = "127.0.0.1:0"\n'
                          f'channel = "{prefix}-{uuid.uuid4().hex[:8]}"\n')
    process = subprocess.Popen([sys.executable, "-m", "feedbench.commands.cli", "sim", str(config),
                                *options], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                               text=True)
    line = process.stdout.readline()
    assert line.startswith(READY), process.stderr.read()
    return process, {**json.loads(line[len(READY):]), "directory": directory}
