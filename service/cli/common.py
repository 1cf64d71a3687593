"""What every ``maxfs`` verb shares: exit statuses and the server client built from flags and settings."""

from __future__ import annotations

import argparse
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
    from maxfs.service.cli.client import MaxfsClient

    s = Settings()
    return MaxfsClient(args.server or s.server, token=args.token or s.token or None)
