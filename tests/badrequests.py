"""Bad requests as data: each case is a row of setup steps, one request, the status it must get
and a substring of the reason. Setup steps check their own status, so a setup request that is
refused (a 507 from a full disk, say) fails the case with that status and its answer, not with
a ``KeyError`` later. Used by ``test_http_errors.py`` and ``test_hostile.py``.

Paths may hold ``{j}``: the id of the job the setup created (``"0" * 32`` when none did).
Requests carry a user's token by name (``user``, from ``server.tokens``), or none (``user=None``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from http.client import HTTPConnection
from typing import Any

import httpx

from tests.procs import Server, poll_until

NO_JOB = "0" * 32
FINAL = ("done", "failed", "cancelled")


@dataclass(frozen=True)
class Req:
    """One HTTP request. ``declared``: send a ``Content-Length`` of that many bytes and only
    ``content`` (which httpx refuses to do)."""

    method: str
    path: str
    json: Any = None
    content: bytes | None = None
    ctype: str | None = None
    user: str | None = "alice"
    headers: dict[str, str] = field(default_factory=dict)
    declared: int | None = None


@dataclass(frozen=True)
class Step:
    """A setup request and the status it must get. ``keep_id``: its answer's ``id`` becomes
    ``{j}``; ``until``: repeat it (a GET) until the answer's ``state`` is final, which must be
    ``until``."""

    req: Req
    status: int
    keep_id: bool = False
    until: str | None = None


@dataclass(frozen=True)
class Bad:
    name: str
    setup: tuple[Step, ...]
    request: Req
    status: int
    reason: str
    server: str = "main"


def send(server: Server, req: Req, jid: str = NO_JOB) -> httpx.Response:
    path = req.path.format(j=jid)
    headers = dict(req.headers)
    if req.user is not None:
        headers["Authorization"] = f"Bearer {server.tokens[req.user]}"
    if req.ctype is not None:
        headers["Content-Type"] = req.ctype
    if req.declared is not None:
        return _lying(server, req.method, path, headers, req.declared, req.content or b"")
    return httpx.request(
        req.method, server.url + path, headers=headers, json=req.json, content=req.content, timeout=60
    )


def _lying(
    server: Server, method: str, path: str, headers: dict[str, str], declared: int, body: bytes
) -> httpx.Response:
    url = httpx.URL(server.url)
    conn = HTTPConnection(url.host, url.port, timeout=30)
    try:
        conn.putrequest(method, path)
        for k, v in headers.items():
            conn.putheader(k, v)
        conn.putheader("Content-Length", str(declared))
        conn.endheaders(body)
        r = conn.getresponse()
        return httpx.Response(r.status, content=r.read())
    finally:
        conn.close()


def _checked(server: Server, step: Step, jid: str) -> httpx.Response:
    r = send(server, step.req, jid)
    assert r.status_code == step.status, (
        f"setup {step.req.method} {step.req.path.format(j=jid)} answered {r.status_code}, "
        f"not {step.status}: {r.text}"
    )
    return r


def run_setup(server: Server, steps: tuple[Step, ...]) -> str:
    """Run the setup steps, each checked; the job id they made (``NO_JOB`` if none)."""
    jid = NO_JOB
    for step in steps:
        if step.until is None:
            r = _checked(server, step, jid)
        else:
            r = poll_until(
                lambda s=step, j=jid: _checked(server, s, j),
                60,
                f"setup: job {jid} to end {step.until}",
                0.1,
                lambda r: r.json()["state"] in FINAL,
            )
            assert r.json()["state"] == step.until, f"setup: job {jid} ended {r.json()['state']}: {r.text}"
        if step.keep_id:
            jid = r.json()["id"]
    return jid


def check_refused(r: httpx.Response, case: Bad) -> None:
    """The answer is the case's status, with the error shape and the reason."""
    assert r.status_code == case.status, r.text
    body = r.json()
    assert set(body) == {"error", "detail"}
    assert case.reason in body["detail"], body
    if r.status_code == 401:
        assert r.headers["www-authenticate"] == "Bearer"
