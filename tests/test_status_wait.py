"""Waiting for a job: ``GET /jobs/{id}?wait=S`` answers when the job's status changes, and
:meth:`MaxfsClient.wait` uses it, never asking more than once per ``poll`` seconds.

The fast tests drive :class:`JobManager` without a cluster and the client against a fake server
on a fake clock (nothing here measures time); one real server checks the two together.
"""

from __future__ import annotations

import asyncio
import itertools
import json
from pathlib import Path
from typing import Any

import httpx
import pytest

from maxfs.service.cli import client as client_mod
from maxfs.service.cli.client import MaxfsClient
from maxfs.service.http.jobs import MAX_WAITS_PER_USER, JobManager
from maxfs.service.settings import Settings
from maxfs.storage.errors import NotFoundError
from maxfs.storage.layout import JobSpec
from maxfs.storage.params import JobParams
from maxfs.storage.records import JobState, load_record, save_record
from maxfs.storage.tokens import User
from maxfs.worker import synthetic

ALICE, BOB = User("alice"), User("bob")


def _manager(tmp_path: Path) -> tuple[JobManager, str]:
    m = JobManager(Settings(data_dir=tmp_path))
    m.root.mkdir(parents=True)
    spec = JobSpec(
        k=4, height=8, width=8, channels=None, dtype="uint8", lights=synthetic.lights_uniform(4).tolist()
    )
    rec = m.create(spec, JobParams.build(eps=1.0, tile=16), ALICE)
    return m, rec.id


def _set_state(m: JobManager, job_id: str, state: JobState) -> None:
    rec = load_record(m.job_dir(job_id))
    rec.state = state
    save_record(m.job_dir(job_id), rec)


def test_a_waiting_status_request_wakes_when_the_job_changes(tmp_path: Path) -> None:
    m, job = _manager(tmp_path)

    async def go() -> None:
        m.loop = asyncio.get_running_loop()
        _set_state(m, job, JobState.RUNNING)
        waiter = asyncio.create_task(m.wait_change(job, ALICE, 30))
        await asyncio.sleep(0)  # the waiter holds the job's event now
        assert not waiter.done()
        m.changed(job)
        await asyncio.wait_for(waiter, 5)  # woken, not after its 30 s
        # a change from another thread (a run's save in a worker thread) wakes it too
        waiter = asyncio.create_task(m.wait_change(job, ALICE, 30))
        await asyncio.sleep(0)
        await asyncio.to_thread(m.changed, job)
        await asyncio.wait_for(waiter, 5)
        assert not m.changes  # every event is dropped once set

    asyncio.run(go())


def test_a_wait_on_a_job_nothing_runs_answers_at_once(tmp_path: Path) -> None:
    m, job = _manager(tmp_path)

    async def go() -> None:
        m.loop = asyncio.get_running_loop()
        for state in (JobState.CREATED, JobState.DONE, JobState.FAILED, JobState.CANCELLED):
            _set_state(m, job, state)
            await asyncio.wait_for(m.wait_change(job, ALICE, 30), 5)
        _set_state(m, job, JobState.QUEUED)  # an active job without change: waits its time out
        await asyncio.wait_for(m.wait_change(job, ALICE, 0.05), 5)

    asyncio.run(go())


def test_a_wait_on_someone_elses_job_or_a_bad_id_is_not_found_and_keeps_nothing(tmp_path: Path) -> None:
    m, job = _manager(tmp_path)

    async def go() -> None:
        m.loop = asyncio.get_running_loop()
        _set_state(m, job, JobState.RUNNING)
        for user, jid in ((BOB, job), (ALICE, "0" * 32), (ALICE, "../x")):
            with pytest.raises(NotFoundError):
                await m.wait_change(jid, user, 1)
        assert not m.changes

    asyncio.run(go())


def test_one_user_holds_at_most_max_waits_waiting_status_requests(tmp_path: Path) -> None:
    """A waiting status request holds a connection: one token must not hold them by the hundred.
    Beyond :data:`MAX_WAITS_PER_USER` its requests answer at once (a plain status); another user's
    still wait, and a slot freed by a change is usable again."""
    m, job = _manager(tmp_path)
    bob_job = m.create(
        JobSpec(4, 8, 8, None, "uint8", synthetic.lights_uniform(4).tolist()), JobParams.build(eps=1.0), BOB
    ).id

    async def go() -> None:
        m.loop = asyncio.get_running_loop()
        _set_state(m, job, JobState.RUNNING)
        _set_state(m, bob_job, JobState.RUNNING)
        held = [asyncio.create_task(m.wait_change(job, ALICE, 30)) for _ in range(MAX_WAITS_PER_USER)]
        await asyncio.sleep(0)
        assert not any(t.done() for t in held)
        await asyncio.wait_for(m.wait_change(job, ALICE, 30), 1)  # over the cap: at once
        bob = asyncio.create_task(m.wait_change(bob_job, BOB, 30))
        await asyncio.sleep(0)
        assert not bob.done()  # his own slots
        m.changed(job)
        await asyncio.wait_for(asyncio.gather(*held), 5)
        again = asyncio.create_task(m.wait_change(job, ALICE, 30))
        await asyncio.sleep(0)
        assert not again.done()  # the slots came back
        m.changed(job)
        m.changed(bob_job)
        await asyncio.wait_for(asyncio.gather(again, bob), 5)

    asyncio.run(go())


class FakeServer:
    """A job that runs ``runs_for`` seconds of a fake clock and saves its progress every
    ``every`` seconds. With ``long_poll`` it answers a status request with ``wait`` at its next
    change (the clock moves on to it), as the server does; without, at once (an older server)."""

    def __init__(self, runs_for: float, every: float, long_poll: bool) -> None:
        self.now, self.runs_for, self.every, self.long_poll = 0.0, runs_for, every, long_poll
        self.asked: list[tuple[float, float]] = []  # (clock, wait) of every status request

    def state(self) -> str:
        return "done" if self.now >= self.runs_for else "running"

    def handler(self, request: httpx.Request) -> httpx.Response:
        wait = float(request.url.params.get("wait", 0))
        self.asked.append((self.now, wait))
        self.now += 0.001  # the request itself
        if self.long_poll and wait > 0 and self.state() == "running":
            nxt = (int(self.now / self.every) + 1) * self.every
            self.now = min(nxt, self.now + wait)
        return httpx.Response(200, content=json.dumps({"id": "j", "state": self.state()}))

    def client(self, monkeypatch: pytest.MonkeyPatch) -> MaxfsClient:
        c = MaxfsClient("http://fake")
        c.http = httpx.Client(base_url="http://fake", transport=httpx.MockTransport(self.handler))

        def sleep(s: float) -> None:
            assert s >= 0
            self.now += s

        monkeypatch.setattr(client_mod.time, "monotonic", lambda: self.now)
        monkeypatch.setattr(client_mod.time, "sleep", sleep)
        return c


@pytest.mark.parametrize("long_poll", [True, False], ids=["long-poll", "older-server"])
@pytest.mark.parametrize("every", [0.02, 1.0, 30.0])
def test_a_long_wait_asks_at_most_once_per_poll_interval(
    monkeypatch: pytest.MonkeyPatch, long_poll: bool, every: float
) -> None:
    fake = FakeServer(runs_for=600.0, every=every, long_poll=long_poll)
    seen: list[dict[str, Any]] = []
    st = fake.client(monkeypatch).wait("j", poll=0.5, on_status=seen.append)
    assert st["state"] == "done" and len(seen) == len(fake.asked)
    times = [t for t, _ in fake.asked]
    gaps = [b - a for a, b in itertools.pairwise(times)]
    assert min(gaps) >= 0.5 - 1e-9  # never two requests within one poll interval
    assert len(times) <= 600.0 / 0.5 + 2
    if long_poll:
        # every request lets the server hold it (bounded), and the end is seen when it comes
        assert all(0 < w <= client_mod.LONG_POLL for _, w in fake.asked)
        assert fake.now - fake.runs_for < 0.01
    else:  # an older server ignores wait: asked every poll seconds, as before
        assert fake.now - fake.runs_for <= 0.5 + 0.01


def test_a_wait_with_a_timeout_never_lets_the_server_hold_it_past_the_timeout(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    fake = FakeServer(runs_for=1e9, every=1e6, long_poll=True)
    with pytest.raises(TimeoutError, match="still running"):
        fake.client(monkeypatch).wait("j", poll=0.5, timeout=25.0)
    assert fake.now <= 25.0 + 0.5 + 0.01
    assert all(t + w <= 25.0 + 1e-6 for t, w in fake.asked)


def test_a_real_server_answers_a_waiting_status_with_the_change(
    server_factory: Any, tmp_path: Path, scene: Any
) -> None:
    sc = scene("bump", 12, 64)
    srv = server_factory(tmp_path / "data", workers=1)
    with MaxfsClient(srv.url) as c:
        job = c.create_job(
            k=12, height=64, width=64, dtype="float32", lights=sc.lights.tolist(), eps=1.0, tile=32
        )["id"]
        # a job nothing runs answers at once, whatever the wait
        assert c.status(job, wait=30)["state"] == "created"
        with pytest.raises(Exception, match="422"):
            c.status(job, wait=31)  # past the longest wait: a clear 4xx, not a held connection
        for i in range(12):
            c.upload_image(job, i, sc.images[i].astype("float32"))
        c.start(job)
        states = []
        st = c.wait(job, on_status=lambda s: states.append(s["state"]))
        assert st["state"] == "done" and states[-1] == "done"
        assert c.status(job, wait=30)["state"] == "done"  # a finished job: at once
        # the typed forms, whose models the client imports only where it uses them
        assert c.job(job).state == "done" and [j.id for j in c.job_list()] == [job]
