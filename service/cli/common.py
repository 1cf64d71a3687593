"""What every ``maxfs`` verb shares: exit statuses and the server client built from flags and settings."""

from __future__ import annotations

import argparse
import sys
from typing import Any

from maxfs.service.settings import Settings

EXIT_NOT_DONE = 1
EXIT_USAGE = 2
EXIT_SERVER = 3
EXIT_STATUSES = (
    "exit status: 0 ok; 1 a job ended without being done (run, demo, wait); 2 usage or bad input "
    "(including the server refusing a request, 4xx); 3 the server failed (5xx) or cannot be reached"
)


def make_client(args: argparse.Namespace) -> Any:
    """A :class:`~maxfs.service.cli.client.MaxfsClient` for ``--server``/``--token`` or their settings."""
    skip_trio()
    from maxfs.service.cli.client import MaxfsClient

    s = Settings()
    return MaxfsClient(args.server or s.server, token=args.token or s.token or None)


def skip_trio() -> None:
    """Keep httpcore (under httpx) from importing trio in this process.

    httpcore imports trio, where it is installed, when the first client is made, only to
    choose its async locks; that costs ~0.07 s of every client command (``submit``, ``status``,
    ``wait``, ``fetch``, ...). trio comes with selenium (the test extra) and other tools, not with
    maxfs. The CLI's client is synchronous and never runs under trio, so it is skipped: a ``None``
    entry in ``sys.modules`` makes ``import trio`` raise ImportError, which httpcore takes as
    "not installed". Only in a ``maxfs`` command's own process, and never over a trio already loaded.
    """
    sys.modules.setdefault("trio", None)  # type: ignore[arg-type]
