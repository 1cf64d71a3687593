"""``maxfs run`` starts the embedded cluster's fork server as soon as it knows the run goes to
Dask with a fresh output (:func:`service.cli.main._prefetch`), and only then."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import pytest

import maxfs.service.cli.main as cli
from maxfs.service.runs import forkserver
from maxfs.service.settings import Settings
from maxfs.storage import stack


@pytest.mark.parametrize(
    ("nbytes", "cluster", "scheduler", "existing", "launched"),
    [
        (10, "", "", False, False),  # in process: the stack is decoded instead
        (1 << 40, "", "", False, True),  # too big to hold: the embedded cluster
        (1 << 40, "", "", True, False),  # resuming: the cluster starts once the store is checked
        (1 << 40, "address", "tls://127.0.0.1:1", False, False),  # no local workers
    ],
)
def test_fork_server_starts_early_only_for_a_fresh_embedded_cluster_run(
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    nbytes: int,
    cluster: str,
    scheduler: str,
    existing: bool,
    launched: bool,
) -> None:
    calls: list[int] = []
    monkeypatch.setattr(forkserver, "launch", lambda: calls.append(1))
    monkeypatch.setattr(stack, "StackReader", lambda ds, threads: "decoding")
    out = tmp_path / "out"
    if existing:
        out.mkdir()
        (out / "something").write_text("x")
    ds = SimpleNamespace(nbytes=nbytes, k=2, height=4, width=4)
    got = cli._prefetch(ds, out, Settings(), scheduler, cluster, 2)
    assert calls == ([1] if launched else [])
    assert (got == "decoding") == (nbytes == 10)
