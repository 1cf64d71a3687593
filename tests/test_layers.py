"""The layers point one way, and no modules import each other in a circle.

``maxfs.service`` -> ``maxfs.worker`` -> ``maxfs.storage`` -> nothing of ours: ``worker``
computes (the Dask tile task reads and writes the store through ``storage``), ``storage``
owns the formats on disk and the shared vocabulary (``storage.options``, ``storage.outputs``,
``storage.errors``), ``service`` speaks HTTP and the CLI above both. Inside ``service``:
``runs`` (job lifecycle) and ``results`` (what is made from finished arrays) know nothing of
``http`` or ``cli``. Checked on the source (every import statement, also inside functions)
and on what importing a module really loads.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
#: source folder -> its installed package name
PACKAGES = {
    "maxfs": "maxfs",
    "storage": "maxfs.storage",
    "worker": "maxfs.worker",
    "service": "maxfs.service",
}

#: folder -> module prefixes its modules must never import
FORBIDDEN: dict[str, set[str]] = {
    "storage": {
        "maxfs.worker",
        "maxfs.service",
        "maxfs.api",
        "tests",
        "bench",
        "fastapi",
        "starlette",
        "uvicorn",
        "numba",
        "highspy",
    },
    "worker": {"maxfs.service", "maxfs.api", "tests", "bench", "fastapi", "starlette", "uvicorn"},
    "service/runs": {"maxfs.service.http", "maxfs.service.cli", "fastapi", "starlette"},
    "service/results": {"maxfs.service.http", "maxfs.service.cli", "maxfs.service.runs", "fastapi"},
    "service/http": {"maxfs.service.cli"},
    "service": {"tests", "bench", "maxfs.api"},
    "maxfs": {"tests", "bench", "fastapi", "maxfs.service.http"},
    # tests may use bench's nothing; benches reuse the test harness (real processes) but no test module
    "bench": {"tests.test_"},
    "tests": {"bench"},
    # the installed names are maxfs.*: a bare "service" would load the folder from the working directory
    "*": {"service", "worker", "storage"},
}


def _module_name(path: Path) -> str:
    rel = path.relative_to(ROOT).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    if parts[0] in PACKAGES:
        return ".".join([PACKAGES[parts[0]], *parts[1:]])
    return ".".join(parts)


def _imports(path: Path) -> list[tuple[int, str]]:
    """(line, dotted module) of every import in a file, relative imports resolved."""
    tree = ast.parse(path.read_text(), filename=str(path))
    pkg = _module_name(path).split(".")
    if path.name != "__init__.py":
        pkg = pkg[:-1]
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = ".".join(pkg[: len(pkg) - node.level + 1])
                mod = f"{base}.{node.module}" if node.module else base
            else:
                mod = node.module or ""
            out.append((node.lineno, mod))
            # "from maxfs.service.cli import verbs" imports the module maxfs.service.cli.verbs
            out += [(node.lineno, f"{mod}.{a.name}") for a in node.names if _is_module(f"{mod}.{a.name}")]
    return out


def _is_module(dotted: str) -> bool:
    return dotted in _all_modules()


def _all_modules() -> dict[str, Path]:
    if not hasattr(_all_modules, "cache"):
        found = {}
        for folder in (*PACKAGES, "tests", "bench"):
            for p in sorted((ROOT / folder).rglob("*.py")):
                found[_module_name(p)] = p
        _all_modules.cache = found  # type: ignore[attr-defined]
    return _all_modules.cache  # type: ignore[attr-defined]


def _matches(mod: str, prefix: str) -> bool:
    return mod == prefix or mod.startswith(prefix + ".") or (prefix.endswith("_") and mod.startswith(prefix))


def _rules_for(path: Path) -> set[str]:
    rel = path.relative_to(ROOT).as_posix()
    rules = set(FORBIDDEN["*"])
    for folder, banned in FORBIDDEN.items():
        if folder != "*" and rel.startswith(folder + "/"):
            rules |= banned
    return rules


@pytest.mark.parametrize("folder", sorted(k for k in FORBIDDEN if k != "*"))
def test_imports_point_one_way(folder: str) -> None:
    bad = []
    for path in sorted((ROOT / folder).rglob("*.py")):
        rules = _rules_for(path)
        for line, mod in _imports(path):
            if any(_matches(mod, r) for r in rules):
                bad.append(f"{path.relative_to(ROOT)}:{line} imports {mod}")
    assert not bad, "imports against the layers:\n" + "\n".join(bad)


def test_no_import_cycles() -> None:
    """No module imports, directly or through others, a module that imports it (also inside functions)."""
    modules = _all_modules()
    graph: dict[str, set[str]] = {}
    for name, path in modules.items():
        deps = set()
        for _, mod in _imports(path):
            # the deepest of our modules the import names (a package's __init__ counts as the package)
            while mod and mod not in modules:
                mod = mod.rpartition(".")[0]
            if mod and mod != name and not name.startswith(mod + "."):
                deps.add(mod)
        graph[name] = deps
    cycles: list[list[str]] = []
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(n: str) -> None:
        state[n] = 1
        stack.append(n)
        for d in sorted(graph[n]):
            if state.get(d) == 1:
                cycles.append([*stack[stack.index(d) :], d])
            elif d not in state:
                visit(d)
        stack.pop()
        state[n] = 2

    for n in sorted(graph):
        if n not in state:
            visit(n)
    assert not cycles, "import cycles:\n" + "\n".join(" -> ".join(c) for c in cycles)


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
        (
            "maxfs.storage.params",
            {"numba", "highspy", "maxfs.worker", "maxfs.service", "distributed", "fastapi"},
        ),
        (
            "maxfs.storage.layout",
            {"numba", "highspy", "maxfs.worker", "maxfs.service", "distributed", "fastapi"},
        ),
        ("maxfs.storage.options", {"numpy", "numba", "highspy", "zarr", "maxfs.worker", "maxfs.service"}),
        # every maxfs command imports these: the client commands need no numpy (~0.15 s each)
        ("maxfs.service.cli.main", {"numpy", "zarr", "numba", "pydantic", "fastapi", "maxfs.worker"}),
        ("maxfs.service.cli.client", {"numpy", "zarr", "numba", "pydantic", "fastapi", "maxfs.worker"}),
        # a dataset folder's camera (K.txt), read by `maxfs submit` before anything is solved
        ("maxfs.worker.camera", {"numba", "zarr", "highspy", "maxfs.service"}),
        ("maxfs.storage.outputs", {"numba", "highspy", "zarr", "maxfs.worker", "maxfs.service"}),
        ("maxfs.worker.task", {"maxfs.service", "fastapi", "uvicorn", "starlette"}),
        # the in-process runner of `maxfs run --solver l2`: numba only once the exact solver runs
        ("maxfs.service.runs.inprocess", {"numba", "highspy", "distributed", "fastapi", "scipy"}),
        ("maxfs", {"numba", "distributed", "fastapi", "uvicorn", "highspy"}),
    ],
)
def test_importing_loads_no_upper_layer(module: str, must_not_load: set[str]) -> None:
    code = f"import sys, {module}; print(' '.join(sorted(sys.modules)))"
    out = subprocess.run([sys.executable, "-c", code], cwd="/", capture_output=True, text=True, check=True)
    loaded = set(out.stdout.split())
    hit = sorted(m for m in loaded for bad in must_not_load if _matches(m, bad))
    assert not hit, f"importing {module} loads {hit[:10]}"
