"""The ``maxfs`` script's entry point: a quiet Ctrl-C from the first instant.

Importing the command line (numpy, the settings) takes a moment; a Ctrl-C then would print a
traceback of the import. So the script's first code is this module, standard library only: it
answers SIGINT with one line and exit status 130 until :func:`maxfs.service.cli.main.console` is imported,
whose own handlers take over from there (same line, same status).
"""

from __future__ import annotations

import os
import signal
import sys


def _quiet(signum: int, frame: object) -> None:
    sys.stderr.write("\nmaxfs: interrupted\n")
    sys.stderr.flush()
    os._exit(130)


def console() -> None:
    """Install the quiet handler, import the CLI, hand SIGINT back to Python, run it."""
    signal.signal(signal.SIGINT, _quiet)
    from maxfs.service.cli.main import console as run

    signal.signal(signal.SIGINT, signal.default_int_handler)
    run()
