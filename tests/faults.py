"""Faults a test injects into the processes it starts (see ``tests/inject/sitecustomize.py``)."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

INJECT = Path(__file__).resolve().parent / "inject"


def fault_env(**faults: Any) -> dict[str, str]:
    """Environment for a process (and the workers it spawns) with ``faults`` injected:
    ``fail_tiles=PATH``, ``free_bytes=N``, ``pause_mask_write=True``."""
    path = os.pathsep.join(p for p in (str(INJECT), os.environ.get("PYTHONPATH", "")) if p)
    return {"PYTHONPATH": path, "MAXFS_TESTS_FAULTS": json.dumps(faults, default=str)}
