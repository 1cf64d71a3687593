"""The docs say what the code does: generated tables current, file references real, the README short."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from maxfs.service.reference import MARK, TABLES, render

ROOT = Path(__file__).resolve().parents[1]
DOCS = sorted((ROOT / "docs").glob("*.md"))


@pytest.mark.parametrize("page", DOCS, ids=lambda p: p.name)
def test_generated_tables_match_the_code(page: Path) -> None:
    text = page.read_text()
    assert text == render(text), f"{page.name} is stale: run python -m maxfs.service.reference docs"


def test_every_generated_table_is_somewhere() -> None:
    found = {m.group(2) for p in DOCS for m in MARK.finditer(p.read_text())}
    assert found == set(TABLES)


def test_every_setting_is_documented() -> None:
    from maxfs.service.reference import _field_docs

    undocumented = [name for name, doc in _field_docs().items() if not doc]
    assert not undocumented


@pytest.mark.parametrize("page", [ROOT / "README.md", *DOCS], ids=lambda p: p.name)
def test_referenced_files_exist(page: Path) -> None:
    """Every repository path a page names (``worker/exact.py``, ``docs/method.md``) exists."""
    text = page.read_text()
    refs = set(
        re.findall(
            r"(?<![\w/.-])((?:service|worker|storage|tests|bench|deploy|docker|docs|maxfs)/[\w/.-]*\w)", text
        )
    )
    missing = sorted(r for r in refs if not (ROOT / r).exists() and not (page.parent / r).exists())
    assert not missing, f"{page.name} names files that do not exist: {missing}"


def test_readme_is_for_users() -> None:
    text = (ROOT / "README.md").read_text()
    assert len(text.encode()) <= 10_500
    head = text.splitlines()[:12]
    assert any("maxfs demo" in line for line in head) and any("pytest" in line for line in head)
