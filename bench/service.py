"""Throughput of the service paths against the in-process solver, in one run.

Rows: the in-process solver (one process, no Dask); the ``maxfs run`` path
(job store + Dask tile tasks on an embedded cluster) with 1 and 2 workers; and
the HTTP path (``maxfs serve`` with 2 embedded workers: upload, start, poll).
Rates count masked-in pixels over the compute phase (job start to last tile;
cluster start-up and upload are excluded and reported separately).

Then, each with interleaved runs and min / median / max (``--runs``; ``--baseline REPO`` runs
another checkout's ``REPO/.venv/bin/maxfs`` in turn with this one, for before/after figures):

- ``server``: a warm ``maxfs serve`` (``maxfs submit --wait`` + ``maxfs fetch``) against
  ``maxfs run`` on the same folder (``--folder``, default the DiLiGenT cat crop);
- ``client``: CPU seconds (user + system) of each client command against one warm server:
  ``submit`` (decode and upload the folder, no wait), ``status``, ``wait``, ``jobs``, ``fetch``
  of a finished job (what a command costs besides the server's work: mostly its start);
- ``dask``: ``maxfs run`` on its Dask path (``MAXFS_IN_PROCESS_BYTES=0``) against the in-process
  path on a 1-megapixel 16-bit job (:func:`bench.scale.write_stack`, ``--mp-k`` images);
- ``store``: a folder's images stored as an upload stores them, then the eps estimate read from
  the store (what a server job does before its tiles), in each version's interpreter;
- ``upload``: HTTP upload MB/s of raw and of PNG bodies (16-bit 1000 x 1000 images), one
  request per image (and PNG with two requests in flight, as two threads of a client send them:
  the server decodes one while it stores the other), and of raw images several to a request as
  ``maxfs submit`` sends them (``PUT /jobs/{id}/images``; "-" for a version without it).

Run: ``python -m bench.service`` (``--only paths,server,client,store,dask,upload``; ``--size``, ``--k``,
``--tile`` change the paths table's job).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from maxfs.service.cli.client import MaxfsClient, upload_batches
from maxfs.service.runs.local import ingest, run_store
from maxfs.storage.datasets import write_npy_folder
from maxfs.storage.errors import MaxfsError
from maxfs.storage.inputs import load_folder
from maxfs.storage.params import JobParams
from maxfs.worker import synthetic
from maxfs.worker.solve import solve
from tests.harness import Server

HERE = Path(sys.executable).parent
CAT = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "diligent-crop8" / "catPNG"


def paths_table(args: argparse.Namespace) -> None:
    """The throughput table of the module docstring."""
    tmp = Path(tempfile.mkdtemp(prefix="maxfs-bench-"))
    try:
        sc = synthetic.bump_scene(args.k, args.size)
        images = sc.images.astype(np.uint8)
        folder = write_npy_folder(tmp / "input", images, sc.lights, sc.mask)
        px = int(sc.mask.sum())
        solve(images[:, :8, :8], sc.lights, eps=args.eps)  # JIT warm-up
        t0 = time.perf_counter()
        solve(images, sc.lights, sc.mask, eps=args.eps, tile=args.tile)
        rows = [("in-process solve()", 1, px / (time.perf_counter() - t0), float("nan"))]

        params = JobParams.build(eps=args.eps, tile=args.tile)
        for workers in (1, 2):
            out = tmp / f"run{workers}.zarr"
            ingest(load_folder(folder), out, params)
            t0 = time.perf_counter()
            rec = run_store(out, workers=workers)
            wall = time.perf_counter() - t0
            compute = rec.finished_at - rec.started_at
            rows.append((f"maxfs run, {workers} worker(s)", workers, px / compute, wall - compute))

        logs = tmp / "logs"
        logs.mkdir()
        server = Server(tmp / "data", "", logs, workers=2)
        try:
            with MaxfsClient(server.url) as c:
                t0 = time.perf_counter()
                job = c.create_job(
                    k=args.k,
                    height=args.size,
                    width=args.size,
                    dtype="uint8",
                    lights=sc.lights.tolist(),
                    eps=args.eps,
                    tile=args.tile,
                )
                for i in range(args.k):
                    c.upload_image(job["id"], i, images[i])
                c.upload_mask(job["id"], sc.mask)
                upload = time.perf_counter() - t0
                c.start(job["id"])
                st = c.wait(job["id"], poll=0.2)
                assert st["state"] == "done", st
                rows.append(
                    ("HTTP (maxfs serve), 2 workers", 2, px / (st["finished_at"] - st["started_at"]), upload)
                )
        finally:
            server.kill()
    finally:
        shutil.rmtree(tmp, ignore_errors=True)

    base = rows[0][2]
    one = rows[1][2]
    print(
        f"bump scene k={args.k}, {args.size}x{args.size} ({px} object pixels), "
        f"tile {args.tile}, eps {args.eps}\n"
    )
    print(
        "| path | workers | pixels/s | per worker vs in-process | vs 1 worker "
        "| overhead outside compute (s) |"
    )
    print("|---|---|---|---|---|---|")
    for name, w, rate, extra in rows:
        over = "-" if np.isnan(extra) else f"{extra:.1f}"
        print(f"| {name} | {w} | {rate:,.0f} | {rate / w / base:.2f}x | {rate / one:.2f}x | {over} |")


def spread(xs: list[float]) -> str:
    return f"{min(xs):.2f} / {statistics.median(xs):.2f} / {max(xs):.2f}"


def interleaved(runs: int, cases: dict[str, Callable[[int], float]]) -> dict[str, list[float]]:
    """Each case ``runs`` times, in turn (a, b, c, a, b, c, ...), so that the load of a shared
    machine falls on all of them alike; every case returns the figure it measured."""
    got: dict[str, list[float]] = {name: [] for name in cases}
    for r in range(runs):
        for name, case in cases.items():
            got[name].append(case(r))
    return got


#: CPU seconds (user + system, the command and every process it waited for) of each
#: :func:`timed_cli` call, in order: the Dask path's workers are the run's children, or the
#: children of its fork server, which outlives the run by a moment (see :func:`_reap_orphans`).
CPU: list[float] = []


def _reap_orphans(limit: float = 10.0) -> None:
    """Wait for the processes a command left behind: this process is a child subreaper, so they
    became its children, and their CPU (with their own children's) counts in RUSAGE_CHILDREN once
    waited for. Stops when no child is left, or after ``limit`` seconds."""
    end = time.monotonic() + limit
    while time.monotonic() < end:
        try:
            pid, _ = os.waitpid(-1, os.WNOHANG)
        except ChildProcessError:
            return
        if pid == 0:
            time.sleep(0.02)


def _be_subreaper() -> None:
    """Orphaned descendants of the commands (an embedded cluster's fork server) become children
    of this process (Linux ``PR_SET_CHILD_SUBREAPER``), so :func:`timed_cli` can count their CPU."""
    import ctypes

    ctypes.CDLL(None, use_errno=True).prctl(36, 1, 0, 0, 0)


def timed_cli(argv: list[str], env: dict[str, str] | None = None) -> float:
    """Wall seconds of one command (its CPU seconds appended to :data:`CPU`); raises with its
    output when it fails."""
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    p = subprocess.run(argv, capture_output=True, text=True, env={**os.environ, **(env or {})})
    wall = time.perf_counter() - t0
    _reap_orphans()
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    CPU.append(r1.ru_utime + r1.ru_stime - r0.ru_utime - r0.ru_stime)
    if p.returncode != 0:
        raise RuntimeError(f"{' '.join(argv)} failed ({p.returncode}):\n{p.stdout}\n{p.stderr}")
    return wall


def serve(bin_dir: Path, root: Path, workers: int) -> Server:
    """``BIN/maxfs serve`` without auth, its data and log in ``root``, progress saved at the
    default interval (the test harness saves it ten times as often)."""
    (root / "logs").mkdir(parents=True, exist_ok=True)
    return Server(
        root / "data",
        "",
        root / "logs",
        workers=workers,
        env={"MAXFS_PROGRESS_INTERVAL": "1"},
        bin_dir=bin_dir,
    )


def versions(args: argparse.Namespace) -> dict[str, Path]:
    """The ``bin`` folders to measure: this checkout's, and ``--baseline``'s before it."""
    out = {}
    if args.baseline:
        out["before"] = Path(args.baseline).resolve() / ".venv" / "bin"
    out["after" if args.baseline else "this"] = HERE
    return out


def server_ratio(args: argparse.Namespace, tmp: Path) -> None:
    """A warm server's ``submit --wait`` + ``fetch`` against ``maxfs run`` on one folder. With
    ``--baseline``, both versions' servers run at once and the four cases take turns (before's run
    and server, after's run and server, again ...), so a shared machine's load falls on all alike."""
    folder = Path(args.folder).resolve()
    servers: dict[str, Server] = {}
    cases: dict[str, Callable[[int], float]] = {}
    try:
        for label, bin_dir in versions(args).items():
            srv = servers[label] = serve(bin_dir, tmp / f"srv-{label}", args.workers)
            url = ["--server", srv.url]

            def local(r: int, b: Path = bin_dir, lab: str = label) -> float:
                return timed_cli([str(b / "maxfs"), "run", str(folder), "-o", str(tmp / f"run-{lab}-{r}")])

            def served(r: int, b: Path = bin_dir, lab: str = label, u: list[str] = url) -> float:
                t0 = time.perf_counter()
                maxfs = str(b / "maxfs")
                sub = subprocess.run(
                    [maxfs, "submit", str(folder), *u, "--name", f"bench-{r}", "--wait"],
                    capture_output=True,
                    text=True,
                    check=True,
                )
                job = sub.stdout.strip().splitlines()[0]
                out = tmp / f"fetch-{lab}-{r}"
                subprocess.run([maxfs, "fetch", job, *u, "-o", str(out)], capture_output=True, check=True)
                wall = time.perf_counter() - t0
                subprocess.run([maxfs, "delete", job, *u], capture_output=True, check=True)
                return wall

            cases[f"{label} run"], cases[f"{label} server"] = local, served
        got = interleaved(args.runs, cases)
    finally:
        for srv in servers.values():
            srv.stop()
    for label in servers:
        run, srv = got[f"{label} run"], got[f"{label} server"]
        ratios = [s / r for s, r in zip(srv, run, strict=True)]
        print(f"| {label} | {spread(run)} | {spread(srv)} | {spread(ratios)} |", flush=True)


#: The client commands of the ``client`` section, after ``submit``; ``JOB`` and ``OUT`` are filled in.
CLIENT_VERBS = {
    "status": ["status", "JOB"],
    "wait": ["wait", "JOB"],
    "jobs": ["jobs"],
    "fetch": ["fetch", "JOB", "-o", "OUT"],
}


def client_costs(args: argparse.Namespace, tmp: Path) -> None:
    """CPU of each client command of each version, against one server of this checkout (the
    client is what differs), the versions in turn. ``submit`` sends the folder with a fresh
    ``--eps`` each time (a new label: no reuse of an earlier job), and the job is deleted after."""
    folder = Path(args.folder).resolve()
    srv = serve(HERE, tmp / "srv-client", args.workers)
    url = ["--server", srv.url]
    got: dict[tuple[str, str], list[float]] = {}
    bins = versions(args)
    try:
        first = subprocess.run(
            [str(HERE / "maxfs"), "submit", str(folder), *url, "--wait"],
            capture_output=True,
            text=True,
            check=True,
        )
        job = first.stdout.split()[0]
        n = 0
        for _ in range(args.runs):
            for label, bin_dir in bins.items():
                maxfs = str(bin_dir / "maxfs")
                n += 1
                timed_cli(
                    [
                        maxfs,
                        "submit",
                        str(folder),
                        *url,
                        "--name",
                        f"client-{n}",
                        "--eps",
                        f"{1 + n / 100:.2f}",
                    ]
                )
                got.setdefault((label, "submit"), []).append(CPU[-1])
                mine = subprocess.run(
                    [maxfs, "jobs", *url, "--json"], capture_output=True, text=True, check=True
                )
                sent = next(j["id"] for j in json.loads(mine.stdout) if j.get("name") == f"client-{n}")
                # not solved: the server's work would fall on the commands measured next
                for verb in ("cancel", "wait", "delete"):
                    subprocess.run([maxfs, verb, sent, *url], capture_output=True)
                for verb, argv in CLIENT_VERBS.items():
                    filled = [
                        job if a == "JOB" else str(tmp / f"fetch-{n}") if a == "OUT" else a for a in argv
                    ]
                    timed_cli([maxfs, *filled, *url])
                    got.setdefault((label, verb), []).append(CPU[-1])
    finally:
        srv.stop()
    for verb in ["submit", *CLIENT_VERBS]:
        print(
            f"| `maxfs {verb}` | " + " | ".join(spread(got[(lab, verb)]) for lab in bins) + " |", flush=True
        )


def dask_ratio(args: argparse.Namespace, tmp: Path) -> None:
    """``maxfs run`` on the Dask path against the in-process path, one 1-megapixel job."""
    from bench.scale import write_stack

    folder = write_stack(tmp / "mp", args.mp_k, 1000)
    _be_subreaper()
    cases: dict[str, Callable[[int], float]] = {}
    cpu: dict[str, list[float]] = {}
    for label, bin_dir in versions(args).items():
        for path, env in (("in-process", {}), ("Dask", {"MAXFS_IN_PROCESS_BYTES": "0"})):
            name = f"{label} {path}"
            cpu[name] = []

            def case(r: int, b: Path = bin_dir, e: dict = env, name: str = name) -> float:
                wall = timed_cli([str(b / "maxfs"), "run", str(folder), "-o", str(tmp / f"{name}-{r}")], e)
                cpu[name].append(CPU[-1])
                return wall

            cases[name] = case
    got = interleaved(args.runs, cases)
    for label in versions(args):
        a, b = got[f"{label} in-process"], got[f"{label} Dask"]
        ratios = [y / x for x, y in zip(a, b, strict=True)]
        ca, cb = cpu[f"{label} in-process"], cpu[f"{label} Dask"]
        print(
            f"| {label} | {spread(a)} | {spread(b)} | {spread(ratios)} | "
            f"{statistics.median(cb) / statistics.median(ca):.2f} |",
            flush=True,
        )


def upload_rates(args: argparse.Namespace, tmp: Path) -> None:
    """MB/s of image uploads, raw little-endian and PNG, to a server of each version."""
    import imagecodecs

    from bench.scale import write_stack

    if args.upload_folder:  # the folder's first images, as decoded (PNG bodies re-encoded)
        ds = load_folder(args.upload_folder)
        k = min(args.upload_k, ds.k)
        images = np.stack([ds.read(i) for i in range(k)])
    else:
        k = args.upload_k
        images = np.load(write_stack(tmp / "up", k, 1000) / "images.npy")
    pngs = [bytes(imagecodecs.png_encode(im)) for im in images]
    h, w, channels = images.shape[1], images.shape[2], (images.shape[3] if images.ndim == 4 else 1)
    lights = synthetic.lights_uniform(k).tolist()
    meta = dict(k=k, height=h, width=w, channels=channels, dtype=str(images.dtype), lights=lights, eps=5.0)
    servers = {label: serve(b, tmp / f"up-{label}", 1) for label, b in versions(args).items()}
    try:

        def send(url: str, raw: bool, batched: bool = False, in_flight: int = 1) -> float:
            with MaxfsClient(url) as c:
                job = c.create_job(**meta)["id"]
                t0 = time.perf_counter()
                if batched:  # as maxfs submit sends them (PUT /jobs/{id}/images), where the server can
                    try:
                        for batch in upload_batches(list(range(k)), images[0].nbytes):
                            c.upload_images(job, batch[0], list(images[batch[0] : batch[-1] + 1]))
                    except MaxfsError:
                        c.delete(job)
                        return float("nan")  # a version without the batch upload

                def one(i: int) -> None:
                    if raw:
                        c.upload_image(job, i, images[i])
                    else:
                        r = c.http.put(
                            f"/jobs/{job}/images/{i}", content=pngs[i], headers={"Content-Type": "image/png"}
                        )
                        assert r.status_code == 200, r.text

                with ThreadPoolExecutor(in_flight) as pool:  # in_flight requests at a time
                    list(pool.map(one, range(k if not batched else 0)))
                wall = time.perf_counter() - t0
                c.delete(job)
            return (images.nbytes if raw else sum(map(len, pngs))) / 2**20 / wall

        cases: dict[str, Callable[[int], float]] = {}
        for label, srv in servers.items():
            cases[f"{label} raw"] = lambda r, u=srv.url: send(u, True)
            cases[f"{label} png"] = lambda r, u=srv.url: send(u, False)
            cases[f"{label} batched"] = lambda r, u=srv.url: send(u, True, batched=True)
            cases[f"{label} png2"] = lambda r, u=srv.url: send(u, False, in_flight=2)
        got = interleaved(args.runs, cases)
    finally:
        for srv in servers.values():
            srv.stop()
    ratio = images.nbytes / sum(map(len, pngs))
    for label in servers:
        b = got[f"{label} batched"]
        batched = "-" if any(np.isnan(b)) else spread(b)
        print(
            f"| {label} | {spread(got[f'{label} raw'])} | {spread(got[f'{label} png'])} "
            f"| {spread(got[f'{label} png2'])} | {batched} | {ratio:.2f} |",
            flush=True,
        )


#: What ``store`` runs in each version's interpreter: the server's side of a job before its tiles,
#: through the API both versions have. Prints "store-seconds eps-seconds".
STORE_STEPS = """
import sys, time
from pathlib import Path
from maxfs.storage.inputs import load_folder
from maxfs.storage.layout import JobSpec, JobStore
from maxfs.storage.params import JobParams
from maxfs.worker.task import estimate_eps_of
ds = load_folder(Path(sys.argv[1]))
images = [ds.read(i) for i in range(ds.k)]
store = JobStore.create(Path(sys.argv[2]), JobSpec.of(ds), JobParams.build(tile=int(sys.argv[3])))
if ds.mask is not None:
    store.write_mask(ds.mask)
t0 = time.perf_counter()
for i, image in enumerate(images):
    store.write_image(i, image)
t1 = time.perf_counter()
estimate_eps_of(store)
print(t1 - t0, time.perf_counter() - t1)
"""


def store_steps(args: argparse.Namespace, tmp: Path) -> None:
    """Storing a folder's images as an upload does (:meth:`JobStore.write_image`), then the eps
    estimate from the store (as its task reads it), in each version's interpreter in turn."""
    folder = Path(args.folder).resolve()
    cases: dict[str, Callable[[int], float]] = {}
    got_eps: dict[str, list[float]] = {}
    for label, bin_dir in versions(args).items():
        got_eps[label] = []

        def steps(r: int, b: Path = bin_dir, lab: str = label) -> float:
            out = tmp / f"store-{lab}-{r}"
            p = subprocess.run(
                [str(b / "python"), "-c", STORE_STEPS, str(folder), str(out), str(args.tile)],
                capture_output=True,
                text=True,
                check=True,
            )
            shutil.rmtree(out, ignore_errors=True)
            stored, eps = (float(v) for v in p.stdout.split())
            got_eps[lab].append(eps)
            return stored

        cases[label] = steps
    got = interleaved(args.runs, cases)
    for label in cases:
        print(f"| {label} | {spread(got[label])} | {spread(got_eps[label])} |", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", default="paths,server,dask,upload", help="sections, comma-separated")
    ap.add_argument("--k", type=int, default=24)
    ap.add_argument("--size", type=int, default=384)
    ap.add_argument("--tile", type=int, default=64)
    ap.add_argument("--eps", type=float, default=1.0)
    ap.add_argument("--runs", type=int, default=3, help="interleaved runs of each case")
    ap.add_argument("--baseline", default="", help="another checkout (with .venv) to measure in turn")
    ap.add_argument("--folder", default=str(CAT), help="the folder of the server section")
    ap.add_argument("--workers", type=int, default=2, help="the server section's workers")
    ap.add_argument("--mp-k", type=int, default=16, help="images of the 1-megapixel Dask-path job")
    ap.add_argument("--upload-k", type=int, default=8, help="images per upload run")
    ap.add_argument(
        "--upload-folder", default="", help="upload this folder's images (default: 1000^2 uint16)"
    )
    args = ap.parse_args()
    only = set(args.only.split(","))
    if "paths" in only:
        paths_table(args)
    tmp = Path(tempfile.mkdtemp(prefix="maxfs-bench-"))
    try:
        if "server" in only:
            print(
                f"\nwarm server (`maxfs submit --wait` + `maxfs fetch`) vs `maxfs run` on {args.folder}; "
                f"wall s, min / median / max of {args.runs} interleaved runs\n"
            )
            print("| version | maxfs run s | server s | server / run |\n|---|---|---|---|", flush=True)
            server_ratio(args, tmp)
        if "client" in only:
            print(
                f"\nclient commands against a warm server, {args.folder}; CPU s (user + system), "
                f"min / median / max of {args.runs} interleaved runs\n"
            )
            labels = list(versions(args))
            print("| command | " + " | ".join(labels) + " |\n|---|" + "---|" * len(labels), flush=True)
            client_costs(args, tmp)
        if "store" in only:
            print(
                f"\nstoring {args.folder}'s images in a job store (tile {args.tile}), then the eps estimate "
                f"from it; s, min / median / max of {args.runs} interleaved runs\n"
            )
            print("| version | store the images s | eps estimate s |\n|---|---|---|", flush=True)
            store_steps(args, tmp)
        if "dask" in only:
            print(
                f"\n`maxfs run`, 1000 x 1000 x {args.mp_k} uint16: Dask path (MAXFS_IN_PROCESS_BYTES=0) vs "
                f"in-process; wall s, min / median / max of {args.runs} interleaved runs\n"
            )
            print(
                "| version | in-process s | Dask s | Dask / in-process | CPU, medians: Dask / in-process |\n"
                "|---|---|---|---|---|",
                flush=True,
            )
            dask_ratio(args, tmp)
        if "upload" in only:
            what = args.upload_folder or "1000 x 1000 uint16"
            print(
                f"\nHTTP upload of {args.upload_k} images of {what} (one user, one at a time); "
                f"MB/s of request body, min / median / max of {args.runs} interleaved runs\n"
            )
            print(
                "| version | raw MB/s | PNG MB/s | PNG, 2 in flight MB/s | raw, batched MB/s "
                "| raw / PNG bytes |\n|---|---|---|---|---|---|",
                flush=True,
            )
            upload_rates(args, tmp)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
