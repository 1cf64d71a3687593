"""Where the shared real datasets are, and the marker for tests that need them.

The data lives in ``../shared`` beside the checkout (CI has it there; `.ci/run`
fails without it). A developer without it gets a skip that says what is missing,
never a confusing failure.
"""

from __future__ import annotations

from pathlib import Path

import pytest

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data"
UW = SHARED / "uw-psm"
UW_OBJECTS = ("buddha", "cat", "chrome", "gray", "horse", "owl", "rock")
DILIGENT = SHARED / "diligent-crop8"

#: Decorate tests that read ``../shared/data``.
needs_shared = pytest.mark.skipif(
    not (UW / "lights.txt").exists(),
    reason=f"needs the shared datasets at {SHARED} (clone the project with ../shared beside it)",
)
