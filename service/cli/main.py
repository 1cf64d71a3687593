"""The ``maxfs`` command line: run a folder locally, serve, and talk to a server."""

from __future__ import annotations

import argparse
import difflib
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from maxfs.service.cli.common import EXIT_NOT_DONE, EXIT_SERVER, EXIT_STATUSES, EXIT_USAGE
from maxfs.service.cli.common import make_client as _client
from maxfs.service.settings import LOOPBACK, Settings, cluster_kind, cluster_settings, runs_in_process
from maxfs.storage.errors import ConflictError, InvalidInputError, MaxfsError
from maxfs.storage.options import INTRINSICS, SOLVE_OPTIONS
from maxfs.storage.params import DEPTH_FIELDS
from maxfs.storage.records import JobState
from maxfs.storage.tokens import TokenStore

#: Exit statuses: 1 a job ended without being done (``run``, ``demo``, ``wait``); 2 usage or bad
#: input (argparse's own, and every refusal that is the request's fault: a 4xx answer, a bad folder);
#: 3 the server failed (a 5xx answer) or cannot be reached.
#: When this process started (near enough: the ``maxfs`` script imports this module first), for
#: the wall time a user waited, as ``done: ... in X s`` says.
STARTED = time.monotonic()


#: What ``-o`` of ``run`` is, and the STORE of ``eval``/``export``: one folder, said one way.
OUTPUT_HELP = (
    "output folder: it holds results.zarr/ (the arrays), previews/ and maxfs-job.json; "
    "running again into it resumes"
)
STORE_HELP = "a result folder (the -o of maxfs run or fetch), holding results.zarr/"


def _eps(value: str) -> float | str:
    if value == "auto":
        return value
    try:
        v = float(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"eps must be a positive number or 'auto', got {value!r}") from None
    if not v > 0:
        raise argparse.ArgumentTypeError(f"eps must be positive, got {value}")
    return v


def _at_least_one(name: str) -> Callable[[str], int]:
    """An argparse type: a whole number of at least 1 (a count of workers, images, pixels)."""

    def parse(value: str) -> int:
        try:
            v = int(value)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{name} must be a whole number, got {value!r}") from None
        if v < 1:
            raise argparse.ArgumentTypeError(f"{name} must be at least 1, got {v}")
        return v

    return parse


def _or_auto(kind: type, name: str) -> Callable[[str], Any]:
    """An argparse type: a number of ``kind``, or the word ``auto``."""
    what = "a whole number" if kind is int else "a number"

    def parse(value: str) -> Any:
        if value == "auto":
            return value
        try:
            return kind(value)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{name} must be {what} or 'auto', got {value!r}") from None

    return parse


def _solver_args(p: argparse.ArgumentParser) -> None:
    """One flag per row of :data:`storage.options.SOLVE_OPTIONS` (the HTTP fields come from
    the same rows); values are checked by :meth:`JobParams.build`, the one validator."""
    for o in SOLVE_OPTIONS:
        shown = f" (default: {o.default})" if o.default is not None else ""
        kw: dict[str, Any] = {"default": o.default, "help": (o.help + shown).replace("%", "%%")}
        if o.kind == "choice":
            kw["choices"] = list(o.choices)
        elif o.kind == "bool":
            kw["action"] = argparse.BooleanOptionalAction
        elif o.name == "eps":
            kw["type"] = _eps
        elif o.kind.endswith("|auto"):
            kw["type"] = _or_auto(int if o.kind.startswith("int") else float, o.name)
        else:
            kw["type"] = {"float": float, "int": int}[o.kind]
        p.add_argument(o.flag, **kw)


def _images_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--images",
        default=None,
        help="use only these images, numbered from 1 in the folder's order, e.g. 1-20,25",
    )


def _cluster_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--cluster",
        choices=["local", "slurm", "address"],
        default=None,
        help="where tiles run: embedded cluster, SLURM worker jobs (MAXFS_SLURM_*), or --scheduler "
        "(default: MAXFS_CLUSTER, else address when a scheduler is given, else local)",
    )


def _server_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--server", default=None, help="server URL (default: MAXFS_SERVER)")
    p.add_argument("--token", default=None, help="API token (default: MAXFS_TOKEN)")


def _params(args: argparse.Namespace) -> dict[str, Any]:
    """The solve options given (or defaulted) on the command line, by name; the camera from the
    dataset folder's ``K.txt`` when it has one and no intrinsics are given."""
    from maxfs.worker.camera import folder_camera

    kw = {o.name: v for o in SOLVE_OPTIONS if (v := getattr(args, o.name, None)) is not None}
    if getattr(args, "folder", None) and not any(n in kw for n in INTRINSICS):
        kw |= folder_camera(args.folder)
    return kw


def _depth_args(p: argparse.ArgumentParser) -> None:
    """The depth rows of :data:`storage.options.SOLVE_OPTIONS` as flags that default to the job's."""
    for o in SOLVE_OPTIONS:
        if o.name in DEPTH_FIELDS:
            kw: dict[str, Any] = {"default": None, "help": o.help + " (default: as the job asked)"}
            kw |= {"choices": list(o.choices)} if o.kind == "choice" else {"type": float}
            p.add_argument(o.flag, **kw)


def _progress() -> Any:
    """A fresh progress display (tqdm on a terminal, plain lines otherwise) for one run."""
    from maxfs.service.cli.verbs import Progress

    return Progress().record


def _dataset(args: argparse.Namespace) -> Any:
    """The input folder, restricted to ``--images``; warns about badly conditioned lights."""
    from maxfs.storage.folders import conditioning_warning, parse_selection, select_images
    from maxfs.storage.inputs import load_folder

    ds = load_folder(args.folder)
    if getattr(args, "images", None) is not None:
        ds = select_images(ds, parse_selection(args.images, ds.k))
    for warning in (conditioning_warning(ds.lights), *ds.notes):
        if warning:
            print(f"maxfs: WARNING: {warning}", file=sys.stderr)
    return ds


def _prefetch(ds: Any, out: Path, settings: Settings, scheduler: str, cluster: str, workers: int) -> Any:
    """Start decoding the stack (:class:`storage.stack.StackReader`) when the run will surely
    need it in memory: a fresh output, the in-process path (no cluster, a stack of at most
    ``MAXFS_IN_PROCESS_BYTES``); None otherwise (a re-run decodes nothing). A fresh output on the
    embedded Dask cluster starts its workers' fork server instead, which loads the solver while
    this process imports the run's modules (the cluster start waits for it)."""
    from maxfs.storage.stack import StackReader

    fresh = not out.exists() or (out.is_dir() and not any(out.iterdir()))
    chosen = cluster_settings(scheduler, workers, cluster)
    if fresh and runs_in_process(chosen, ds.nbytes, settings.in_process_bytes):
        return StackReader(ds, workers)
    if fresh and cluster_kind(chosen) == "local":
        from maxfs.service.runs import forkserver

        forkserver.launch()
    return None


def cmd_run(args: argparse.Namespace) -> int:
    from maxfs.service.runs.timings import Timings

    tm = Timings()
    settings = Settings()
    with tm.phase("open the folder"):
        ds = _dataset(args)
    scheduler = args.scheduler if args.scheduler is not None else settings.scheduler
    cluster = args.cluster if args.cluster is not None else settings.cluster
    workers = args.workers or settings.workers
    prefetch = _prefetch(ds, Path(args.output), settings, scheduler, cluster, workers)
    with tm.phase("imports"):  # while the images are decoded (prefetch)
        from maxfs.service.runs.local import run_folder
        from maxfs.storage.layout import JobSpec
        from maxfs.storage.requests import job_params, tile_is_auto

    spec = JobSpec.of(ds)
    options = _params(args)
    params = job_params(spec, options, settings.task_memory, ds.mask)
    print(f"{ds.name}: {ds.k} images of {ds.height} x {ds.width} ({ds.layout}, {ds.dtype})", file=sys.stderr)
    store, rec = run_folder(
        ds,
        Path(args.output),
        params,
        overwrite=args.overwrite,
        scheduler=scheduler,
        cluster=cluster,
        workers=workers,
        in_process_bytes=settings.in_process_bytes,
        on_note=lambda note: print(note, file=sys.stderr),
        on_progress=_progress(),
        timings=tm,
        prefetch=prefetch,
        tile_auto=tile_is_auto(options),
    )
    if args.timings:
        print(tm.table(), file=sys.stderr)
    if rec.state is not JobState.DONE:
        print(f"maxfs: job {rec.state.value}: {rec.error or ''}".rstrip(": "), file=sys.stderr)
        return EXIT_NOT_DONE
    solving = (rec.finished_at or 0) - (rec.started_at or 0)
    from maxfs.service.cli.verbs import raw_step_words

    print(
        f"done: {rec.pixels_done} masked pixels in {time.monotonic() - STARTED:.1f} s "
        f"({solving:.1f} s solving), eps={rec.eps:.4g}{raw_step_words(rec.raw_step)}, "
        f"tile={store.params.tile}; {shares(rec)}; results in {store.path} (previews/ has PNGs)"
    )
    _warn(rec)
    _report_ground_truth(args, store.path)
    return 0


def shares(rec: Any) -> str:
    """'solved 99.1 %, certified optimal 98.7 %' for a record: shares of all masked pixels."""
    from maxfs.service.cli.verbs import share_words

    return share_words(
        rec.solved_share, rec.certified_share, rec.unfinished_pixels, rec.pixels_total
    ) + suspect(rec.calibration)


def suspect(calibration: list[str]) -> str:
    """' but calibration suspect: ...' after a certified share when a calibration check tripped
    (an optimum proved for wrong lights is still wrong), naming the first reason."""
    if not calibration:
        return ""
    more = f" (and {len(calibration) - 1} more, below)" if len(calibration) > 1 else ""
    return f" but calibration suspect: {calibration[0].split(':')[0]}{more}"


def _warn(rec: Any) -> None:
    for w in rec.warnings():
        print(f"maxfs: WARNING: {w}", file=sys.stderr)


def _report_ground_truth(args: argparse.Namespace, out: Path) -> None:
    """``run --gt``, or the dataset folder's own ``Normal_gt.mat``: print the angular error."""
    from maxfs.service.results.research import evaluate_store, find_ground_truth
    from maxfs.storage.layout import JobStore

    store = JobStore.open(out, mode="r")
    if store.has_array("depth"):
        a = store.array_meta("depth").attrs
        print(f"depth: {a['pixels']} pixels, residual RMS {a['residual_rms']:.3g} px", file=sys.stderr)
    gt = args.gt or find_ground_truth(args.folder)
    if gt:
        ev, map_path, json_path = evaluate_store(out, gt)
        print(f"vs {gt}: {ev.summary()}; error map {map_path}, numbers {json_path}")


def cmd_export(args: argparse.Namespace) -> int:
    from maxfs.service.results.export import ITEMS, export

    items = tuple(args.only.split(",")) if args.only else ITEMS
    if args.no_mesh:
        items = tuple(i for i in items if i != "mesh")
    depth = {n: v for n in DEPTH_FIELDS if (v := getattr(args, n)) is not None}
    m = export(
        args.store,
        args.output,
        items=items,
        mesh_formats=tuple(args.mesh_format.split(",")),
        jump=args.jump,
        depth_options=depth,
    )
    if m["tiles_done"] < m["tiles_total"]:
        print(
            f"maxfs: WARNING: {m['tiles_total'] - m['tiles_done']} of {m['tiles_total']} tiles are not "
            "finished; their pixels are empty in the export",
            file=sys.stderr,
        )
    for name, info in m["files"].items():
        extra = ", ".join(f"{k} {v}" for k, v in info.items() if k in ("vertices", "faces", "scale"))
        print(f"{m['folder']}/{name}" + (f"  ({extra})" if extra else ""))
    return 0


def cmd_eval(args: argparse.Namespace) -> int:
    from maxfs.service.results.research import evaluate_store

    ev, map_path, json_path = evaluate_store(
        args.store, args.gt, max_deg=args.max_deg, map_path=args.map, json_path=args.json_out
    )
    if args.json:
        print(json_path.read_text(), end="")
    else:
        print(ev.summary())
        print(f"error map: {map_path}\nJSON: {json_path}", file=sys.stderr)
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    import numpy as np

    from maxfs.service.runs.local import run_folder
    from maxfs.storage.datasets import write_npy_folder
    from maxfs.storage.inputs import load_folder
    from maxfs.storage.layout import JobStore
    from maxfs.storage.options import DEFAULT_EPS, DEFAULT_MODEL
    from maxfs.storage.params import JobParams
    from maxfs.worker import synthetic

    out = Path(args.output)
    scene = synthetic.bump_scene(args.k, args.size, noise=0.0)
    folder = write_npy_folder(out / "input", scene.images.astype(np.uint8), scene.lights, scene.mask)
    print(
        f"demo: synthetic cast-shadow scene, {args.k} images of {args.size}^2, in {folder}", file=sys.stderr
    )
    store, rec = run_folder(
        load_folder(folder),
        out / "result",
        # the defaults of `maxfs run` (storage.options), so the demo shows what a run does
        JobParams.build(eps=DEFAULT_EPS, model=DEFAULT_MODEL, tile=args.tile),
        workers=args.workers or Settings().workers,
        on_note=lambda note: print(note, file=sys.stderr),
        on_progress=_progress(),
    )
    if rec.state is not JobState.DONE:
        print(f"maxfs: demo job {rec.state.value}: {rec.error}", file=sys.stderr)
        return EXIT_NOT_DONE
    normal = JobStore.open(store.path, mode="r").read_output("normal")
    err = synthetic.angular_error_deg(normal, scene.normals)[scene.mask]
    print(
        f"demo done: mean angular error {np.nanmean(err):.3f} deg over {err.size} pixels; "
        f"results in {store.path}"
    )
    return 0


def compile_bytecode(packages: tuple[str, ...] = ("maxfs",)) -> int:
    """Byte-compile every module of ``packages`` (and their subpackages) beside its source, as
    ``pip install`` does for a wheel; returns the modules compiled now.

    An editable install (the README's) has no ``.pyc`` until a module is imported with bytecode
    writing on, and where ``PYTHONDONTWRITEBYTECODE`` is set (many CI and container images) never:
    every command then compiles some 60 modules from source, about 0.15 s of CPU each time.
    ``compileall`` writes them regardless, and imports read them (timestamps are checked, so an
    edited source is compiled again). A folder that is not writable is left as it is."""
    import compileall
    import importlib.util
    import io
    from contextlib import redirect_stdout

    done = 0
    for name in packages:
        spec = importlib.util.find_spec(name)
        for folder in (spec.submodule_search_locations or []) if spec else []:
            for path in [Path(folder), *(p.parent for p in Path(folder).rglob("*/__init__.py"))]:
                if not os.access(path, os.W_OK):
                    continue
                with redirect_stdout(io.StringIO()) as said:  # it names each file it compiles
                    compileall.compile_dir(path, maxlevels=0, quiet=0)
                done += said.getvalue().count("Compiling ")
    return done


def cmd_warm(args: argparse.Namespace) -> int:
    from maxfs.worker.task import load_kernels

    load = load_kernels()
    how = "compiled and cached" if load.compiled else "loaded from the cache"
    print(f"solver kernels ready: {how} in {load.seconds:.1f} s")
    from maxfs.worker import lts_kernel  # the response estimate's LTS

    lts_kernel.warm_up()
    # the depth step's kernels too (a few seconds to compile once after an install), for the normals'
    # float32 as a run stores them
    from maxfs.worker import depth_scenes
    from maxfs.worker.depth import integrate

    t = time.perf_counter()
    scene = depth_scenes.sphere_ortho(16)
    integrate(scene.normal, scene.mask, method="bini", max_iterations=2)
    print(f"depth kernels ready in {time.perf_counter() - t:.1f} s")
    # each subpackage's folder: the installed package maps maxfs.worker etc. to their own folders
    n = compile_bytecode(("maxfs", "maxfs.storage", "maxfs.worker", "maxfs.service"))
    print(f"bytecode ready ({n} modules compiled now)")
    return 0


def cmd_serve(args: argparse.Namespace) -> int:
    import uvicorn

    from maxfs.service.cli.gc_policy import usual_collections
    from maxfs.service.http.app import create_app

    usual_collections()  # a server is long-lived: CPython's collection thresholds, not a CLI's

    overrides = {
        k: v
        for k, v in {
            "host": args.host,
            "port": args.port,
            "data_dir": args.data_dir,
            "workers": args.workers,
            "scheduler": args.scheduler,
            "cluster": args.cluster,
            "auth": False if args.no_auth else None,
        }.items()
        if v is not None
    }
    settings = Settings(**overrides)
    from maxfs.service.runs.cluster import cluster_kind

    cluster_kind(settings)  # an unknown --cluster, or address without a scheduler: refused before starting
    check_port_free(settings.host, settings.port)  # before the cluster starts, not 30 s later
    if not settings.auth and settings.host not in LOOPBACK:
        raise MaxfsError(
            f"refusing to serve without auth on {settings.host}: anyone who can reach it could read and "
            "cancel every job. Use --host 127.0.0.1, or keep auth on and make tokens "
            "with `maxfs token create`"
        )
    if settings.auth and not TokenStore(settings.tokens_file).users():
        print(
            f"maxfs: auth is on and no API token exists yet; make one with "
            f"`maxfs token create NAME --data-dir {settings.data_dir}` (or serve with --no-auth on loopback)",
            file=sys.stderr,
        )
    from maxfs.service.http.connections import guarded_protocol

    _raise_open_files_limit()
    uvicorn.run(
        create_app(settings),
        http=guarded_protocol(settings.header_timeout, settings.max_connections_per_client),
        host=settings.host,
        port=settings.port,
        log_level="info",
        log_config=_serve_logging(),
        limit_concurrency=settings.max_connections,  # beyond: 503 at once, not a hung accept queue
        timeout_keep_alive=5,
    )
    return 0


def _raise_open_files_limit() -> None:
    """Raise the soft limit of open files to the hard one: every connection is a file, and the
    usual soft limit (1024) is below ``MAXFS_MAX_CONNECTIONS`` plus the server's own files."""
    import resource

    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft != hard:
        try:
            resource.setrlimit(resource.RLIMIT_NOFILE, (hard, hard))
        except (ValueError, OSError):
            pass


def check_port_free(host: str, port: int) -> None:
    """Refuse a ``host:port`` that cannot be listened on (another server holds it), by binding
    it once as uvicorn will (SO_REUSEADDR), before anything slow starts."""
    import socket

    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except socket.gaierror as e:
        raise InvalidInputError(f"cannot listen on {host}:{port}: {e.strerror}; check --host") from None
    family, kind, proto, _, addr = infos[0]
    with socket.socket(family, kind, proto) as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind(addr)
        except OSError as e:
            raise ConflictError(
                f"cannot listen on {host}:{port}: {e.strerror}; another server may be running there. "
                "Stop it, or choose another --port"
            ) from None


def _serve_logging() -> dict:
    """uvicorn's logging, plus the server's own ``maxfs.*`` loggers at INFO with a time stamp
    (job starts and ends, tile failures: what an operator reads when a job seems stuck)."""
    import copy

    from uvicorn.config import LOGGING_CONFIG

    cfg = copy.deepcopy(LOGGING_CONFIG)
    cfg["formatters"]["maxfs"] = {"format": "%(asctime)s %(levelname)s %(name)s: %(message)s"}
    cfg["handlers"]["maxfs"] = {
        "formatter": "maxfs",
        "class": "logging.StreamHandler",
        "stream": "ext://sys.stderr",
    }
    cfg["loggers"]["maxfs"] = {"handlers": ["maxfs"], "level": "INFO", "propagate": False}
    return cfg


def cmd_token(args: argparse.Namespace) -> int:
    overrides = {"data_dir": args.data_dir} if args.data_dir else {}
    tokens = TokenStore(Settings(**overrides).tokens_file)
    if args.action == "create":
        token = tokens.create(args.name, admin=args.admin, replace=args.replace)
        print(token)
        print(
            f"token for {args.name}{' (admin)' if args.admin else ''}; it is shown only now. "
            "Clients send it as 'Authorization: Bearer <token>' or set MAXFS_TOKEN.",
            file=sys.stderr,
        )
    elif args.action == "revoke":
        tokens.revoke(args.name)
        print(f"revoked the token of {args.name}", file=sys.stderr)
    else:
        for u in tokens.users():
            print(f"{u.name}{'  admin' if u.admin else ''}")
    return 0


def cmd_submit(args: argparse.Namespace) -> int:
    from maxfs.service.cli.verbs import UploadProgress, wait_and_report

    ds = _dataset(args)
    with _client(args) as c:
        with UploadProgress(ds.k) as shown:
            job_id = c.submit_folder(
                ds,
                name=args.name,
                existing="reuse" if args.reuse else "refuse",
                on_upload=shown.update,
                **_params(args),
            )
        print(job_id, flush=True)
        if args.wait:
            return wait_and_report(c, job_id, as_json=False)
    return 0


def cmd_status(args: argparse.Namespace) -> int:
    from maxfs.service.cli.verbs import cmd_status as status

    return status(args)


def cmd_fetch(args: argparse.Namespace) -> int:
    with _client(args) as c:
        if args.wait:
            st = c.wait(args.job_id)
            if st["state"] != JobState.DONE and not args.partial:
                raise ConflictError(
                    f"job {args.job_id} ended {st['state']}: {st.get('error') or ''}; its results are "
                    "partial (fetch them with --partial)"
                )
        out = c.fetch_zarr(
            args.job_id, Path(args.output), partial=args.partial, inputs=args.inputs, overwrite=args.overwrite
        )
        print(out)
    return 0


def cmd_delete(args: argparse.Namespace) -> int:
    with _client(args) as c:
        c.delete(args.job_id)
    print(f"deleted {args.job_id}", file=sys.stderr)
    return 0


def cmd_cancel(args: argparse.Namespace) -> int:
    with _client(args) as c:
        print(c.cancel(args.job_id)["state"])
    return 0


def _job_verbs(sub: Any) -> None:
    """``jobs``, ``wait ID``, ``start ID`` (service/cliverbs.py)."""
    from maxfs.service.cli import verbs as cliverbs

    p = sub.add_parser("jobs", help="list your jobs on a server")
    p.add_argument("--json", action="store_true")
    _server_args(p)
    p.set_defaults(fn=cliverbs.cmd_jobs)
    p = sub.add_parser("wait", help="wait for a job to finish, showing progress (exit 1 unless done)")
    p.add_argument("job_id")
    p.add_argument("--json", action="store_true", help="print the final status as JSON")
    _server_args(p)
    p.set_defaults(fn=cliverbs.cmd_wait)
    p = sub.add_parser("start", help="start a job, or resume a cancelled or failed one")
    p.add_argument("job_id")
    p.add_argument("--wait", action="store_true", help="then wait for it to finish")
    p.add_argument("--json", action="store_true")
    _server_args(p)
    p.set_defaults(fn=cliverbs.cmd_start)


def parser() -> argparse.ArgumentParser:
    from maxfs.service.cli.verbs import version

    ap = argparse.ArgumentParser(
        prog="maxfs", description="Robust photometric stereo (exact Max-FS).", epilog=EXIT_STATUSES
    )
    ap.add_argument("--version", action="version", version=f"maxfs {version()}")
    sub = ap.add_subparsers(dest="command", required=True)
    p = sub.add_parser("run", help="run a dataset folder on this machine")
    p.add_argument("folder")
    p.add_argument("-o", "--output", required=True, help=OUTPUT_HELP)
    _solver_args(p)
    p.add_argument("--scheduler", default=None, help="Dask scheduler address (default: embedded cluster)")
    _cluster_arg(p)
    p.add_argument(
        "--workers", type=_at_least_one("--workers"), default=None, help="embedded cluster worker processes"
    )
    p.add_argument(
        "--overwrite",
        action="store_true",
        help="replace results in OUTPUT made from other inputs (otherwise refused)",
    )
    p.add_argument("--timings", action="store_true", help="print the time spent in each phase")
    p.add_argument(
        "--gt",
        default=None,
        help="ground-truth normals to report the angular error against (default: "
        "the folder's Normal_gt.mat when present)",
    )
    _images_arg(p)
    p.set_defaults(fn=cmd_run)
    p = sub.add_parser("eval", help="angular error of a result against ground-truth normals")
    p.add_argument("store", help=STORE_HELP)
    p.add_argument("--gt", required=True, help="Normal_gt.mat (DiLiGenT), .npy (H, W, 3) or (n+1)/2 PNG")
    p.add_argument("--max-deg", type=float, default=45.0, help="top of the error map's colour scale")
    p.add_argument("--map", default=None, help="error map PNG (default: STORE/previews/angular_error-GT.png)")
    p.add_argument("--json-out", default=None, help="statistics file (default: STORE/maxfs-eval-GT.json)")
    p.add_argument("--json", action="store_true", help="print the statistics as JSON")
    p.set_defaults(fn=cmd_eval)
    p = sub.add_parser("export", help="write results as PNG/NPY/TIFF images and a PLY/OBJ mesh")
    p.add_argument("store", help=STORE_HELP)
    p.add_argument(
        "-o",
        "--output",
        default=None,
        help="folder for the exported files (default: STORE-export beside STORE)",
    )
    p.add_argument("--only", default=None, help="comma list of normal,albedo,inlier_count,depth,mesh")
    p.add_argument("--no-mesh", action="store_true", help="skip the mesh")
    p.add_argument("--mesh-format", default="ply,obj", help="ply, obj or ply,obj (default)")
    p.add_argument(
        "--jump",
        type=float,
        default=2.0,
        help="the mesh is not joined where depth is off its normals by more than this many pixels (2)",
    )
    _depth_args(p)
    p.set_defaults(fn=cmd_export)
    p = sub.add_parser("demo", help="make a synthetic dataset and run it")
    p.add_argument("-o", "--output", default="maxfs-demo")
    p.add_argument("--k", type=int, default=24)
    p.add_argument("--size", type=int, default=256)
    p.add_argument("--tile", type=int, default=64)
    p.add_argument("--workers", type=_at_least_one("--workers"), default=None)
    p.set_defaults(fn=cmd_demo)
    p = sub.add_parser(
        "warm", help="compile the solver for this machine now (else the first run after an install does)"
    )
    p.set_defaults(fn=cmd_warm)
    p = sub.add_parser("serve", help="run the HTTP server")
    p.add_argument("--host", default=None, help="address to listen on (default: MAXFS_HOST, else 127.0.0.1)")
    p.add_argument("--port", type=int, default=None, help="TCP port (default: MAXFS_PORT, else 8000)")
    p.add_argument(
        "--data-dir",
        default=None,
        help="folder for jobs and the token file (default: MAXFS_DATA_DIR, else ./maxfs-data)",
    )
    p.add_argument(
        "--workers",
        type=_at_least_one("--workers"),
        default=None,
        help="worker processes of the embedded cluster (default: MAXFS_WORKERS, else up to 4)",
    )
    p.add_argument("--scheduler", default=None, help="Dask scheduler address (default: embedded cluster)")
    _cluster_arg(p)
    p.add_argument("--no-auth", action="store_true", help="no API tokens (single user, loopback only)")
    p.set_defaults(fn=cmd_serve)
    p = sub.add_parser("token", help="make, list or revoke API tokens of a server's users")
    actions = p.add_subparsers(dest="action", required=True, metavar="{create,list,revoke}")
    for action, help_ in (
        ("create", "make a token for a user and print it (shown only this once)"),
        ("list", "list the users that have a token"),
        ("revoke", "revoke a user's token"),
    ):
        t = actions.add_parser(action, help=help_, description=help_)
        if action != "list":
            t.add_argument("name", help="the user's name")
        if action == "create":
            t.add_argument(
                "--admin", action="store_true", help="the token sees and cancels every user's jobs"
            )
            t.add_argument("--replace", action="store_true", help="replace the user's existing token")
        t.add_argument("--data-dir", default=None, help="the server's data folder (default: MAXFS_DATA_DIR)")
        t.set_defaults(fn=cmd_token)
    for name, fn, help_ in (
        ("status", cmd_status, "show a job's state and progress"),
        ("cancel", cmd_cancel, "cancel a job"),
        ("delete", cmd_delete, "delete a job that is not queued or running, with all its data"),
    ):
        p = sub.add_parser(name, help=help_)
        p.add_argument("job_id")
        _server_args(p)
        p.set_defaults(fn=fn)
        if name == "status":
            p.add_argument("--json", action="store_true", help="the server's full status as JSON")
    _job_verbs(sub)
    p = sub.add_parser("submit", help="send a dataset folder to a server; prints the job id")
    p.add_argument("folder")
    _server_args(p)
    _solver_args(p)
    _images_arg(p)
    p.add_argument("--wait", action="store_true", help="wait for the job to finish, showing progress")
    p.add_argument("--name", default=None, help="what to call the job (default: the folder's name)")
    p.add_argument(
        "--reuse",
        action="store_true",
        help="if a finished job has these inputs and parameters, print its id instead of computing "
        "again (without it such a submit is refused, naming the job)",
    )
    p.set_defaults(fn=cmd_submit)
    p = sub.add_parser("fetch", help="download a job's results as a Zarr folder")
    p.add_argument("job_id")
    p.add_argument(
        "-o",
        "--output",
        required=True,
        help="output folder to create: it will hold results.zarr/ and previews/",
    )
    p.add_argument(
        "--overwrite", action="store_true", help="replace an existing OUTPUT that holds maxfs results"
    )
    p.add_argument("--wait", action="store_true", help="wait until the job has finished, then fetch")
    p.add_argument("--inputs", action="store_true", help="also download the input image stack")
    p.add_argument(
        "--partial", action="store_true", help="fetch a job that is not done (unfinished tiles hold fills)"
    )
    _server_args(p)
    p.set_defaults(fn=cmd_fetch)
    return ap


def _subparser(ap: argparse.ArgumentParser, command: str | None) -> argparse.ArgumentParser:
    """The parser of ``command`` (``token create`` included), or ``ap``."""
    for action in ap._actions:
        if isinstance(action, argparse._SubParsersAction) and command in action.choices:
            return action.choices[command]
    return ap


def parse(argv: list[str] | None = None) -> argparse.Namespace:
    """The command line, with a suggestion for a mistyped option (``--esp``: did you mean ``--eps``?)
    from the parser of the command it was given to, whose usage is shown."""
    ap = parser()
    args, extra = ap.parse_known_args(argv)
    if extra:
        p = _subparser(ap, getattr(args, "command", None))
        if getattr(args, "action", None) and p is not ap:
            p = _subparser(p, args.action)
        known = [o for a in p._actions for o in a.option_strings if o.startswith("--")]
        hints = []
        for word in extra:
            close = difflib.get_close_matches(word.split("=", 1)[0], known, n=1, cutoff=0.6)
            if word.startswith("-") and close:
                hints.append(f"{word}: did you mean {close[0]}?")
        p.error(f"unrecognized arguments: {' '.join(extra)}" + "".join(f"; {h}" for h in hints))
    return args


def _interrupted() -> None:
    print("\nmaxfs: interrupted; run the same command again to resume", file=sys.stderr, flush=True)
    # tiles still running in threads or worker processes would hold the exit (and print
    # tracebacks); their work is not lost: a tile counts only once its done marker is written
    sys.stdout.flush()
    os._exit(130)


def main(argv: list[str] | None = None) -> int:
    try:
        args = parse(argv)
        return int(args.fn(args))
    except MaxfsError as e:
        print(f"maxfs: error: {e}", file=sys.stderr)
        # the client marks errors from the server's answers with their status (service.cli.client)
        return EXIT_SERVER if getattr(e, "http_status", 0) >= 500 else EXIT_USAGE
    except KeyboardInterrupt:
        _interrupted()
    except Exception as e:
        # httpx is imported only by the verbs that talk to a server (0.1 s less for `maxfs run`)
        httpx = sys.modules.get("httpx")
        if httpx is None or not isinstance(e, httpx.HTTPError):
            raise
        print(f"maxfs: error: cannot talk to the server ({e}); is `maxfs serve` running?", file=sys.stderr)
        return EXIT_SERVER


def console() -> None:
    """The ``maxfs`` command: :func:`main`, then a quick exit.

    Once numba's compiled kernels are loaded, the interpreter's own teardown takes about a
    second (measured 0.9 s after loading them, 0.65 s at the end of a ``maxfs run``) and does
    nothing for us: every result is written and closed by then. So when no other thread is
    still at work, the exit handlers run (zarr, logging, temporary folders) and the process
    ends without that teardown; otherwise Python exits as usual.
    """
    import atexit
    import threading

    try:
        code = main()
    except KeyboardInterrupt:  # between main's handlers, e.g. while one prints
        _interrupted()
    # idle pool threads (the shard encoders of a store written, Dask's offload thread) are no work:
    # the pools end them first, as Python's own exit does (a task still running is waited for)
    from concurrent.futures import thread as pool_threads

    pool_threads._python_exit()
    busy = [t for t in threading.enumerate() if t is not threading.main_thread() and not t.daemon]
    if busy:
        sys.exit(code)
    atexit._run_exitfuncs()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


if __name__ == "__main__":
    console()
