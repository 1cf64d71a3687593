"""The layers point one way: ``service`` -> ``worker`` -> ``storage`` -> nothing of ours.

``worker`` computes (the Dask tile task reads and writes the store through ``storage``),
``storage`` owns the formats on disk and the shared vocabulary (``storage.options``,
``storage.outputs``, ``storage.errors``), ``service`` speaks HTTP and the CLI above both.
Checked on the source (every import statement, also inside functions) and on what
importing a module really loads.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

#: package -> top-level names its modules must never import
FORBIDDEN = {
    "storage": {"worker", "service", "tests", "bench", "fastapi", "starlette", "uvicorn", "numba", "highspy"},
    "worker": {"service", "tests", "bench", "fastapi", "starlette", "uvicorn"},
    "service": {"tests", "bench"},
    "bench": {"tests"},
    "tests": {"bench"},
}


def _imports(path: Path) -> list[tuple[int, str]]:
    """(line, dotted module) of every import in a file, relative imports resolved."""
    tree = ast.parse(path.read_text(), filename=str(path))
    pkg = path.parent.relative_to(ROOT).parts
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = ".".join(pkg[: len(pkg) - node.level + 1])
                out.append((node.lineno, f"{base}.{node.module}" if node.module else base))
            else:
                out.append((node.lineno, node.module or ""))
    return out


@pytest.mark.parametrize("package", sorted(FORBIDDEN))
def test_imports_point_one_way(package: str) -> None:
    bad = []
    for path in sorted((ROOT / package).rglob("*.py")):
        for line, mod in _imports(path):
            top = mod.split(".")[0]
            if top in FORBIDDEN[package]:
                bad.append(f"{path.relative_to(ROOT)}:{line} imports {mod}")
    assert not bad, "imports against the layers:\n" + "\n".join(bad)


def test_no_test_module_imports_another() -> None:
    bad = [
        f"{p.name}:{line} imports {mod}"
        for p in sorted((ROOT / "tests").glob("*.py"))
        for line, mod in _imports(p)
        if mod.startswith("tests.test_")
    ]
    why = "test modules share helpers through tests/ helper modules, not each other:\n"
    assert not bad, why + "\n".join(bad)


@pytest.mark.parametrize(
    ("module", "must_not_load"),
    [
        ("storage.params", {"numba", "highspy", "worker", "service", "distributed", "fastapi"}),
        ("storage.layout", {"numba", "highspy", "worker", "service", "distributed", "fastapi"}),
        ("storage.options", {"numba", "highspy", "zarr", "worker", "service"}),
        ("storage.outputs", {"numba", "highspy", "zarr", "worker", "service"}),
        ("worker.task", {"service", "fastapi", "uvicorn", "starlette"}),
    ],
)
def test_importing_loads_no_upper_layer(module: str, must_not_load: set[str]) -> None:
    code = f"import sys, {module}; print(' '.join(sorted({{m.split('.')[0] for m in sys.modules}})))"
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True)
    loaded = set(out.stdout.split())
    assert not loaded & must_not_load, f"importing {module} loads {sorted(loaded & must_not_load)}"
