"""Three users at once on a real server with auth: every job finishes, nobody reaches
another user's job, and status answers while jobs run (latency is reported by
``python -m bench.load``, not asserted here); the scenario is :mod:`tests.loadgen`."""

from __future__ import annotations

from collections.abc import Callable

from tests.loadgen import run_load
from tests.procs import Server


def test_three_users_at_once_all_finish_and_stay_apart(server_factory: Callable[..., Server]) -> None:
    server = server_factory(workers=2, auth=True)
    tokens = {u: server.token(u) for u in ("ann", "ben", "cai")}
    r = run_load(server.url, tokens, jobs_per_user=2, k=8, size=32, timeout=300)
    server.kill()
    assert len(r.states) == 6 and set(r.states.values()) == {"done"}, r.states
    assert r.leaked == [], r.leaked
    assert r.denied == 3 * 4 * 4  # each user x 4 foreign jobs x 4 requests
    assert r.listed_ok
    assert len(r.latencies) > 20, "status was not polled while the jobs ran"
