"""Where the shared real datasets are.

The data lives in ``../shared/data`` beside the checkout (CI has it there; `.ci/run`
fails without it). Tests take it through the ``uw_psm`` and ``diligent`` fixtures
(``tests/conftest.py``): a developer without it gets a skip that names ``../shared``
and says what is missing, never a confusing failure.
"""

from __future__ import annotations

from pathlib import Path

import pytest

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data"
UW = SHARED / "uw-psm"
UW_OBJECTS = ("buddha", "cat", "chrome", "gray", "horse", "owl", "rock")
DILIGENT = SHARED / "diligent-crop8"


def require(folder: Path, marker: str = "") -> Path:
    """``folder`` if it (and ``folder/marker``) exists; else skip, naming ``../shared``."""
    if not (folder / marker).exists():
        pytest.skip(
            f"needs the shared datasets in ../shared/data beside the checkout ({folder / marker} is "
            "missing; clone the project with ../shared beside it)"
        )
    return folder
