"""Reference tables of the docs, generated from the code: settings, solve options, output arrays.

``python -m maxfs.service.reference`` rewrites the tables in ``docs/`` between their markers
(``<!-- generated: NAME -->`` ... ``<!-- end generated -->``); ``tests/test_docs.py`` fails when a
table in the docs differs from what the code says, so a new setting, option or output array
cannot go undocumented.
"""

from __future__ import annotations

import ast
import dataclasses
import inspect
import re
import sys
from collections.abc import Callable
from pathlib import Path

from maxfs.service import settings as settings_module
from maxfs.service.settings import ENV_PREFIX, Settings
from maxfs.storage.options import INTRINSICS, SOLVE_OPTIONS, ModelDefaults
from maxfs.storage.outputs import OUTPUT_TABLE

#: Options whose unset value is the model's (:class:`maxfs.storage.options.ModelDefaults`).
MODEL_FIELDS = frozenset(f.name for f in dataclasses.fields(ModelDefaults))
MARK = re.compile(r"(<!-- generated: (\w+) -->\n)(.*?)(<!-- end generated -->)", re.S)


def _field_docs() -> dict[str, str]:
    """The ``#:`` comment above each Settings field (a comment shared by consecutive fields
    belongs to each of them)."""
    src = inspect.getsource(settings_module)
    cls = next(n for n in ast.parse(src).body if isinstance(n, ast.ClassDef) and n.name == "Settings")
    lines = src.splitlines()
    docs: dict[str, str] = {}
    last = ""
    for node in cls.body:
        if not isinstance(node, ast.AnnAssign) or not isinstance(node.target, ast.Name):
            continue
        above = []
        i = node.lineno - 2
        while i >= 0 and lines[i].strip().startswith("#:"):
            above.insert(0, lines[i].strip()[2:].strip())
            i -= 1
        last = " ".join(above) or last
        docs[node.target.id] = last
    return docs


def _fmt_default(v: object) -> str:
    if isinstance(v, int) and not isinstance(v, bool) and v >= 1 << 20 and v % (1 << 20) == 0:
        return f"{v >> 30} GiB" if v % (1 << 30) == 0 else f"{v >> 20} MiB"
    if v == "":
        return "empty"
    return str(v)


def settings_table() -> str:
    docs = _field_docs()
    rows = ["| variable | default | what |", "|---|---|---|"]
    for f in dataclasses.fields(Settings):
        doc = docs.get(f.name, "").replace("|", "\\|")
        default = "cores, at most 4" if f.name == "workers" else _fmt_default(f.default)
        rows.append(f"| `{ENV_PREFIX}{f.name.upper()}` | {default} | {doc} |")
    return "\n".join(rows) + "\n"


def options_table() -> str:
    rows = ["| option (CLI flag, HTTP field) | kind | default | what |", "|---|---|---|---|"]
    for o in SOLVE_OPTIONS:
        kind = " / ".join(o.choices) if o.choices else o.kind.replace("|", " or ")
        if o.name in MODEL_FIELDS or o.name == "shadow":
            unset = "the model's"
        elif o.name in INTRINSICS or o.name == "distance":
            unset = "none (orthographic)" if o.name in INTRINSICS else "none"
        else:
            unset = "see what"
        default = unset if o.default is None else str(o.default)
        rows.append(f"| `{o.flag}`, `{o.name}` | {kind} | {default} | {o.help.replace('|', '/')} |")
    return "\n".join(rows) + "\n"


def outputs_table() -> str:
    rows = ["| array | dimensions | dtype | fill | made | what |", "|---|---|---|---|---|---|"]
    for o in OUTPUT_TABLE:
        rows.append(
            f"| `{o.name}` | ({', '.join(o.dims)}) | {o.dtype} | {o.fill} | {o.made} | {o.description} |"
        )
    return "\n".join(rows) + "\n"


TABLES: dict[str, Callable[[], str]] = {
    "settings": settings_table,
    "options": options_table,
    "outputs": outputs_table,
}


def render(text: str) -> str:
    """``text`` with every generated table replaced by what the code says now."""
    return MARK.sub(lambda m: m.group(1) + TABLES[m.group(2)]() + m.group(4), text)


def main(argv: list[str]) -> int:
    docs = Path(argv[0]) if argv else Path("docs")
    for p in sorted(docs.glob("*.md")):
        old = p.read_text()
        new = render(old)
        if new != old:
            p.write_text(new)
            print(f"updated {p}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
