"""Load on a shared server: several users submit jobs at once while others poll status.

Each user (one thread) creates its jobs, uploads every image, starts them, and
waits; a poller thread per user reads the status of that user's jobs in a loop
and records each request's latency. At the end every user tries to read, fetch
and cancel every other user's jobs (all must answer 404) and lists its own jobs.

    python -m bench.load [--users 3] [--jobs 3] [--k 12] [--size 64] [--workers 2]

prints one table row: jobs finished, status requests, p50/p95/max status
latency, and cross-user denials. ``tests/test_load.py`` runs the same scenario
small and checks its outcome (never its timings).
"""

from __future__ import annotations

import argparse
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import httpx
import numpy as np

from service.client import FINAL_STATES, MaxfsClient
from worker import synthetic


@dataclass
class LoadResult:
    """What happened under load."""

    states: dict[str, str] = field(default_factory=dict)  # job id -> final state
    owner: dict[str, str] = field(default_factory=dict)  # job id -> user
    latencies: list[float] = field(default_factory=list)  # seconds per status request
    denied: int = 0  # cross-user requests answered 404
    leaked: list[str] = field(default_factory=list)  # cross-user requests that were not
    listed_ok: bool = True  # every user's list held exactly its own jobs
    wall: float = 0.0

    def percentile(self, q: float) -> float:
        return float(np.percentile(self.latencies, q)) if self.latencies else float("nan")


def run_load(
    url: str,
    tokens: dict[str, str],
    jobs_per_user: int = 3,
    k: int = 12,
    size: int = 64,
    timeout: float = 600,
) -> LoadResult:
    """Run the scenario against a server at ``url`` with one token per user."""
    res = LoadResult()
    lock = threading.Lock()
    scene = synthetic.bump_scene(k, size, seed=1)
    images = scene.images.astype(np.uint8)
    mine: dict[str, list[str]] = {u: [] for u in tokens}
    stop = threading.Event()
    errors: list[BaseException] = []

    def submit(user: str) -> None:
        try:
            with MaxfsClient(url, token=tokens[user]) as c:
                for _ in range(jobs_per_user):
                    job = c.create_job(
                        k=k, height=size, width=size, dtype="uint8", lights=scene.lights.tolist(), eps=1.0
                    )
                    for i in range(k):
                        c.upload_image(job["id"], i, images[i])
                    c.upload_mask(job["id"], scene.mask)
                    c.start(job["id"])
                    with lock:
                        mine[user].append(job["id"])
                        res.owner[job["id"]] = user
                for jid in list(mine[user]):
                    res.states[jid] = c.wait(jid, poll=0.2, timeout=timeout)["state"]
        except BaseException as e:  # reported by the caller
            errors.append(e)

    def poll(user: str) -> None:
        with httpx.Client(base_url=url, headers={"Authorization": f"Bearer {tokens[user]}"}) as http:
            while not stop.is_set():
                with lock:
                    ids = list(mine[user])
                for jid in ids:
                    t0 = time.perf_counter()
                    r = http.get(f"/jobs/{jid}")
                    dt = time.perf_counter() - t0
                    if r.status_code != 200:
                        errors.append(RuntimeError(f"status of own job {jid}: {r.status_code} {r.text}"))
                    with lock:
                        res.latencies.append(dt)
                time.sleep(0.01)

    t0 = time.perf_counter()
    submitters = [threading.Thread(target=submit, args=(u,)) for u in tokens]
    pollers = [threading.Thread(target=poll, args=(u,), daemon=True) for u in tokens]
    for t in submitters + pollers:
        t.start()
    for t in submitters:
        t.join()
    stop.set()
    for t in pollers:
        t.join(timeout=30)
    res.wall = time.perf_counter() - t0
    if errors:
        raise errors[0]

    for user, token in tokens.items():
        with httpx.Client(base_url=url, headers={"Authorization": f"Bearer {token}"}) as http:
            listed = {j["id"] for j in http.get("/jobs").json()}
            res.listed_ok &= listed == set(mine[user])
            for jid, owner in res.owner.items():
                if owner == user:
                    continue
                for method, path in (
                    ("GET", f"/jobs/{jid}"),
                    ("GET", f"/jobs/{jid}/results/normal.npy"),
                    ("GET", f"/jobs/{jid}/results.zip"),
                    ("DELETE", f"/jobs/{jid}"),
                ):
                    r = http.request(method, path)
                    if r.status_code == 404:
                        res.denied += 1
                    else:
                        res.leaked.append(f"{user} {method} {path}: {r.status_code}")
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--users", type=int, default=3)
    ap.add_argument("--jobs", type=int, default=3, help="jobs per user")
    ap.add_argument("--k", type=int, default=12)
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args()

    from tests.procs import Server

    with tempfile.TemporaryDirectory(prefix="maxfs-load-") as tmp:
        server = Server(Path(tmp) / "data", "", Path(tmp), workers=args.workers, auth=True)
        try:
            tokens = {f"user{i}": server.token(f"user{i}") for i in range(args.users)}
            r = run_load(server.url, tokens, args.jobs, args.k, args.size)
        finally:
            server.kill()
    done = sum(s == "done" for s in r.states.values())
    print(
        "| users | jobs | k | size | wall s | jobs done | status requests | p50 ms | p95 ms | max ms "
        "| cross-user 404 | leaks |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    print(
        f"| {args.users} | {len(r.states)} | {args.k} | {args.size} | {r.wall:.1f} | {done} "
        f"| {len(r.latencies)} "
        f"| {r.percentile(50) * 1e3:.1f} | {r.percentile(95) * 1e3:.1f} | {max(r.latencies) * 1e3:.1f} "
        f"| {r.denied} | {len(r.leaked)} |"
    )
    assert all(s in FINAL_STATES for s in r.states.values())


if __name__ == "__main__":
    main()
