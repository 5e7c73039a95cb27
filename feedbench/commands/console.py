"""The `feedbench` console script: `cli.main`, with Ctrl-C one line at every moment.

`cli.main` turns a Ctrl-C during the command into one line; this wrapper also covers the
moments around it: while Python still imports the command's modules (numpy, scipy, canopen:
about 0.4 s before `main` runs) and while the interpreter exits after it (atexit handlers,
finalizers), where a Ctrl-C would otherwise print a traceback or "Exception ignored".
"""

from __future__ import annotations

import signal
import sys

INTERRUPTED = 130
"""Exit status after Ctrl-C (128 + SIGINT), as `cli.INTERRUPTED`."""


def run() -> int:
    """Import and run `cli.main`; a Ctrl-C before it is one line; SIGINT ignored after it."""
    try:
        from feedbench.commands.cli import main

        status = main()
    except KeyboardInterrupt:
        if "--debug" in sys.argv[1:]:
            raise
        print("feedbench: error: interrupted", file=sys.stderr)
        status = INTERRUPTED
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the command is over: exit quietly
    return status
