"""Load on a shared server: several users submit jobs at once while others poll status,
and (``--hostile``) a careless or hostile user attacks the server meanwhile.

Each user (one thread) creates its jobs, uploads every image, starts them, and
waits; a poller thread per user reads the status of that user's jobs in a loop
and records each request's latency. At the end every user tries to read, fetch
and cancel every other user's jobs (all must answer 404) and lists its own jobs.

With ``--hostile``, threads send what issue #10 catalogued, in a loop, for as long
as the users work: 56 MB JSON bodies without a token, PNG decompression bombs, stalled
uploads (left to time out), a job of tiny tiles, start/cancel storms on one job, and
slow readers of a large result. Their answers are counted by status code. Then issue #24's
attacks, each on a fresh server of default limits (:mod:`bench.attacks`): 1,000 slow or
silent connections (from one address, and from 20), 300 never-read downloads by one user,
and a data disk (a 24 MB tmpfs; needs root) that fills mid-run.

    python -m bench.load [--users 3] [--jobs 3] [--k 12] [--size 64] [--workers 2] [--hostile]

prints a table row: jobs finished, status requests, p50/p95/max status latency, the
server's peak memory (VmHWM, and its growth during the run), hostile requests by
answer, and cross-user denials. ``tests/test_load.py`` runs the same scenario small
and checks its outcome (never its timings); the scenario is :mod:`tests.loadgen`.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

from maxfs.service.cli.client import FINAL_STATES
from tests.harness import Server
from tests.loadgen import run_load


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--users", type=int, default=3)
    ap.add_argument("--jobs", type=int, default=3, help="jobs per user")
    ap.add_argument("--k", type=int, default=12)
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--hostile", action="store_true", help="a hostile user attacks the server meanwhile")
    args = ap.parse_args()

    with tempfile.TemporaryDirectory(prefix="maxfs-load-") as tmp:
        env = {"MAXFS_UPLOAD_IDLE_TIMEOUT": "5", "MAXFS_MIN_FREE_BYTES": "0"}
        server = Server(Path(tmp) / "data", "", Path(tmp), workers=args.workers, auth=True, env=env)
        try:
            tokens = {f"user{i}": server.token(f"user{i}") for i in range(args.users)}
            bad = server.token("mallory") if args.hostile else None
            base_kb = _kb(server.proc.pid, "VmRSS")
            r = run_load(server.url, tokens, args.jobs, args.k, args.size, hostile_token=bad)
            peak_kb = _kb(server.proc.pid, "VmHWM")
        finally:
            server.kill()
    done = sum(s == "done" for s in r.states.values())
    print(
        "| users | hostile | jobs | k | size | wall s | jobs done | status requests | p50 ms | p95 ms "
        "| max ms | server peak MB (growth) | cross-user 404 | leaks |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    print(
        f"| {args.users} | {'yes' if args.hostile else 'no'} | {len(r.states)} | {args.k} | {args.size} "
        f"| {r.wall:.1f} | {done} | {len(r.latencies)} "
        f"| {r.percentile(50) * 1e3:.1f} | {r.percentile(95) * 1e3:.1f} | {max(r.latencies) * 1e3:.1f} "
        f"| {peak_kb / 1024:.0f} (+{(peak_kb - base_kb) / 1024:.0f}) | {r.denied} | {len(r.leaked)} |"
    )
    if r.hostile:
        print()
        print("| hostile request: answer | count |")
        print("|---|---|")
        for what, n in sorted(r.hostile.items()):
            print(f"| {what} | {n} |")
    assert all(s in FINAL_STATES for s in r.states.values())
    if args.hostile:
        print()
        print("| attack (issue #24) | another client meanwhile | the server |")
        print("|---|---|---|")
        for row in _attacks(args.workers):
            print(f"| {row['attack']} | {row['other client']} | {row['server']} |")


def _attacks(workers: int) -> list[dict]:
    """Slow clients, stalled downloads and a full disk against a server of default limits."""
    from bench import attacks

    rows = []
    with tempfile.TemporaryDirectory(prefix="maxfs-attacks-") as tmp:
        env = {"MAXFS_MIN_FREE_BYTES": "0"}
        server = Server(Path(tmp) / "data", "", Path(tmp), workers=workers, auth=True, env=env)
        try:
            alice, bob = server.token("alice"), server.token("bob")
            for n, addresses in ((1000, 1), (1000, 20)):
                rows.append(attacks.slow_clients(server.url, alice, n, addresses, header_timeout=10.0))
            rows.append(attacks.stalled_downloads(server.url, server.proc.pid, alice, bob, 300))
        finally:
            server.kill()
        logs = Path(tmp)
        rows.append(
            attacks.full_disk(
                lambda data, env: Server(data, "", logs, workers=workers, auth=True, env=env), logs
            )
        )
    return rows


def _kb(pid: int, key: str) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1])
    return 0


if __name__ == "__main__":
    main()
