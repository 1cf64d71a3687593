"""What a user reads (issue 25): each message is checked as the user sees it."""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.stores import finish_a_tile

MAXFS = str(Path(sys.executable).parent / "maxfs")

KERNEL_SOURCE = """
from numba import njit


@njit(cache=True)
def twice(x):
    s = 0.0
    for i in range(x.shape[0]):
        s += 2.0 * x[i]
    return s
"""


def _fresh_module(path: Path, name: str):
    """A new module object from ``path`` (fresh dispatchers: nothing compiled in memory yet)."""
    spec = importlib.util.spec_from_file_location(name, path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


# --- compiling or loading the kernels ----------------------------------------------------------
def test_a_compile_is_told_by_numba_cache_misses_not_by_time(tmp_path: Path) -> None:
    """A cache miss (compile) calls ``on_compile`` and reports ``compiled``; the same kernel in a
    fresh module then loads from numba's cache, however long that takes: no note."""
    import numpy as np

    from maxfs.service.runs.local import COMPILING
    from maxfs.worker.task import kernel_dispatchers, load_kernels

    src = tmp_path / "kern.py"
    src.write_text(KERNEL_SOURCE)
    said: list[str] = []
    first = _fresh_module(src, "kern_a")
    x = np.arange(4.0)

    def slow_compile() -> None:
        first.twice(x)
        time.sleep(0.3)  # the watcher sees the miss while the load still runs

    load = load_kernels(
        lambda: said.append(COMPILING), dispatchers=kernel_dispatchers(first), load=slow_compile, poll=0.02
    )
    assert load.compiled and said == [COMPILING]

    again = _fresh_module(src, "kern_b")

    def slow_cache_load() -> None:  # a busy machine: a cache load that takes long
        again.twice(x)
        time.sleep(0.3)

    load = load_kernels(
        lambda: said.append("again"), dispatchers=kernel_dispatchers(again), load=slow_cache_load, poll=0.02
    )
    assert not load.compiled and load.seconds >= 0.3
    assert said == [COMPILING]
    assert sum(again.twice.stats.cache_hits.values()) == 1


def test_a_failed_kernel_load_raises_and_says_nothing() -> None:
    from maxfs.worker.task import load_kernels

    said: list[str] = []

    def broken() -> None:
        raise RuntimeError("no compiler")

    with pytest.raises(RuntimeError, match="no compiler"):
        load_kernels(lambda: said.append("late"), dispatchers=[], load=broken, poll=0.01)
    time.sleep(0.05)
    assert said == []


@pytest.mark.slow
def test_maxfs_warm_says_loaded_from_the_cache_once_compiled() -> None:
    """After one ``maxfs warm`` (compiled or loaded), a second one loads from numba's cache."""
    subprocess.run([MAXFS, "warm"], capture_output=True, text=True, timeout=600, check=True)
    out = subprocess.run([MAXFS, "warm"], capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr
    assert out.stdout.startswith("solver kernels ready: loaded from the cache in "), out.stdout


def test_warm_byte_compiles_a_package_once_and_again_after_an_edit(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``maxfs warm`` writes every module's bytecode (subpackages too) even where Python would not
    (PYTHONDONTWRITEBYTECODE); a second warm compiles nothing; an edited module is compiled again."""
    from maxfs.service.cli.main import compile_bytecode

    pkg = tmp_path / "warmpkg"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "sub" / "__init__.py").write_text("")
    mod = pkg / "sub" / "mod.py"
    mod.write_text("X = 1\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setattr(sys, "dont_write_bytecode", True)
    assert compile_bytecode(("warmpkg",)) == 3
    assert Path(importlib.util.cache_from_source(str(mod))).is_file()
    assert compile_bytecode(("warmpkg",)) == 0
    mod.write_text("X = 22\n")
    later = mod.stat().st_mtime + 10  # compileall compares whole seconds of mtime
    os.utime(mod, (later, later))
    assert compile_bytecode(("warmpkg",)) == 1
    assert compile_bytecode(("no_such_package_here",)) == 0


# --- images are named as the user numbers them --------------------------------------------------
def test_a_wrong_image_is_named_from_1_with_its_file(tmp_path: Path) -> None:
    import numpy as np

    from maxfs.storage.errors import DatasetError
    from maxfs.storage.folders import select_images
    from maxfs.storage.imageio import encode_png
    from maxfs.storage.inputs import load_folder
    from maxfs.worker import synthetic

    k = 12
    for i in range(k):
        shape = (9, 8) if i == 9 else (8, 8)  # the tenth file, 010.png, has another size
        (tmp_path / f"{i + 1:03d}.png").write_bytes(encode_png(np.full(shape, 100, np.uint8)))
    np.savetxt(tmp_path / "lights.txt", synthetic.lights_uniform(k))
    ds = load_folder(tmp_path)
    with pytest.raises(DatasetError) as e:
        ds.read(9)
    assert "image 10 (010.png) has shape (9, 8) but image 1 (001.png) has (8, 8)" in str(e.value)
    chosen = select_images(ds, [0, 4, 9])  # --images 1,5,10: the numbers stay the folder's
    with pytest.raises(DatasetError, match=r"image 10 \(010\.png\) has shape"):
        chosen.read(2)


# --- shares of the whole mask ------------------------------------------------------------------
def _stopped(state):
    from maxfs.storage.records import JobRecord

    # cancelled at 7 of 20 tiles: every finished pixel solved and certified
    return JobRecord(
        id="j",
        state=state,
        tiles_total=20,
        tiles_done=7,
        pixels_total=20000,
        pixels_done=7000,
        solved_pixels=7000,
        certified_pixels=7000,
    )


def test_a_cancelled_job_reports_shares_of_the_whole_mask() -> None:
    from maxfs.service.cli.main import shares
    from maxfs.service.cli.verbs import format_status
    from maxfs.service.http.models import status_body
    from maxfs.storage.records import JobState

    rec = _stopped(JobState.CANCELLED)
    said = shares(rec)
    assert said == "solved 35.0%, certified optimal 35.0% of all masked pixels (13000 of 20000 not computed)"
    line = format_status(status_body(rec, "http://x"))
    assert "solved 35.0%, certified optimal 35.0% of all masked pixels" in line and "100.0%" not in line
    assert rec.warnings() == []  # unfinished pixels are no sign of a bad result
    done = _stopped(JobState.DONE)
    done.pixels_done = done.solved_pixels = done.certified_pixels = 20000
    assert shares(done) == "solved 100.0%, certified optimal 100.0%"


# --- the job page of a failed job ---------------------------------------------------------------
def test_a_failed_job_says_why_and_offers_no_resume_that_fails_the_same_way() -> None:
    from maxfs.service.http.models import status_body
    from maxfs.storage.records import JobRecord, JobState

    failed = JobRecord(id="j", state=JobState.FAILED, error="eps estimate failed: too dark", tiles_total=4)
    body = status_body(failed, "http://x")
    note = body["results"]["note"]
    assert "failed" in note and "error above" in note and "not been started" not in note
    assert body["results"]["resumable"] is False
    cancelled = _stopped(JobState.CANCELLED)
    assert status_body(cancelled, "http://x")["results"] == {
        "available": False,
        "partial": True,
        "note": "Partial results: cancelled after 7 of 20 tiles; Resume goes on from there.",
        "resumable": True,
    }
    fresh = status_body(JobRecord(id="k"), "http://x")["results"]["note"]
    assert fresh == "No results yet: the job has not been started."


def test_the_job_page_shows_the_note_and_hides_resume_of_a_failed_job() -> None:
    """The page's script reads ``results.note`` and ``results.resumable`` (the body tested above)."""
    js = (Path(__file__).parents[1] / "service" / "static" / "page" / "page.js").read_text()
    assert "job.results.note" in js and "resumable" in js and "not been started" not in js


# --- progress lines ---------------------------------------------------------------------------------
def test_progress_starts_with_counted_tiles_and_weighs_them_by_masked_pixels() -> None:
    import io

    from maxfs.service.cli.verbs import Progress

    out = io.StringIO()
    p = Progress(stream=out)
    p.update(0, 0, "queued")
    assert out.getvalue() == ""  # no "0/0 tiles (0%)" line
    p.update(1, 4, "running", 2000.0, 9.0, pixels=(600, 1000))  # the biggest tile first
    assert out.getvalue() == "1/4 tiles (60% of the masked pixels), running, 2.0k px/s, ETA 00:00:09\n"


# --- the output folder keeps earlier results --------------------------------------------------------
def test_other_parameters_into_an_existing_output_are_refused_and_nothing_is_lost(tmp_path: Path) -> None:
    import numpy as np

    from maxfs.service.runs.local import ingest
    from maxfs.storage.datasets import write_npy_folder
    from maxfs.storage.errors import ConflictError
    from maxfs.storage.inputs import load_folder
    from maxfs.storage.layout import JobStore
    from maxfs.storage.params import JobParams
    from maxfs.worker import synthetic

    sc = synthetic.bump_scene(6, 16, seed=2)
    ds = load_folder(write_npy_folder(tmp_path / "in", sc.images.astype(np.uint8), sc.lights, sc.mask))
    out = tmp_path / "out"
    store, _ = ingest(ds, out, JobParams.build(eps=1.0, tile=16))
    finish_a_tile(store, ds)  # a store with nothing finished would be replaced (test_replacing_outputs)
    with pytest.raises(ConflictError) as e:
        ingest(ds, out, JobParams.build(eps=2.0, tile=16))
    msg = str(e.value)
    assert "other parameters (eps 1.0 -> 2.0)" in msg and "--overwrite" in msg and "-o" in msg
    assert JobStore.open(out, mode="r").params.eps == 1.0  # the earlier run's parameters stay
    store, _ = ingest(ds, out, JobParams.build(eps=2.0, tile=16), overwrite=True)
    assert store.params.eps == 2.0


def test_auto_tile_resumes_on_the_grid_the_job_began_with(tmp_path: Path) -> None:
    """A job begun with another edge (by hand, or by an earlier auto rule) resumes under "auto";
    an edge given by hand that differs is still refused."""
    import numpy as np

    from maxfs.service.runs.local import ingest
    from maxfs.storage.datasets import write_npy_folder
    from maxfs.storage.errors import ConflictError
    from maxfs.storage.inputs import load_folder
    from maxfs.storage.params import JobParams
    from maxfs.storage.requests import tile_is_auto
    from maxfs.worker import synthetic

    assert tile_is_auto({}) and tile_is_auto({"tile": "auto"}) and not tile_is_auto({"tile": 32})
    sc = synthetic.bump_scene(6, 48, seed=2)
    ds = load_folder(write_npy_folder(tmp_path / "in", sc.images.astype(np.uint8), sc.lights, sc.mask))
    out = tmp_path / "out"
    store, _ = ingest(ds, out, JobParams.build(eps=1.0, tile=48))
    finish_a_tile(store, ds)
    store, note = ingest(ds, out, JobParams.build(eps=1.0, tile=32), tile_auto=True)
    assert store.params.tile == 48 and note.startswith("resuming")
    with pytest.raises(ConflictError, match="tile 48 -> 32"):
        ingest(ds, out, JobParams.build(eps=1.0, tile=32))


# --- the command line ---------------------------------------------------------------------------------
def _help(*argv: str, capsys) -> str:
    from maxfs.service.cli.main import main

    with pytest.raises(SystemExit):
        main([*argv, "-h"])
    return capsys.readouterr().out


def test_serve_and_token_create_have_their_own_help(capsys) -> None:
    serve = _help("serve", capsys=capsys)
    for flag, words in (
        ("--host", "address to listen on"),
        ("--port", "TCP port"),
        ("--data-dir", "folder for jobs"),
        ("--workers", "worker processes"),
    ):
        assert words in serve.split(flag, 2)[2], flag
    create = _help("token", "create", capsys=capsys)
    assert create.startswith("usage: maxfs token create [-h] [--admin] [--replace]") and "name" in create


def test_a_mistyped_option_gets_a_suggestion(capsys) -> None:
    from maxfs.service.cli.main import main

    with pytest.raises(SystemExit) as e:
        main(["run", "folder", "-o", "out", "--esp", "2"])
    err = capsys.readouterr().err
    assert e.value.code == 2
    assert err.startswith("usage: maxfs run ") and "--esp: did you mean --eps?" in err


def test_output_folders_are_described_one_way(capsys) -> None:
    run = _help("run", capsys=capsys)
    assert "holds results.zarr/" in " ".join(run.split())
    for verb in ("eval", "export"):
        text = " ".join(_help(verb, "x", capsys=capsys).split())
        assert "holding results.zarr/" in text and "OUT.zarr" not in text


def test_serve_on_a_busy_port_fails_before_starting_anything(tmp_path: Path) -> None:
    import socket

    from maxfs.service.cli.main import check_port_free
    from maxfs.storage.errors import ConflictError

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        with pytest.raises(ConflictError, match=f"cannot listen on 127.0.0.1:{port}.*another --port"):
            check_port_free("127.0.0.1", port)
    check_port_free("127.0.0.1", port)  # free again


@pytest.mark.slow
def test_maxfs_serve_on_a_busy_port_exits_at_once(tmp_path: Path) -> None:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        t0 = time.monotonic()
        r = subprocess.run(
            [MAXFS, "serve", "--no-auth", "--port", str(port), "--data-dir", str(tmp_path)],
            capture_output=True,
            text=True,
            timeout=60,
        )
    assert r.returncode == 2 and f"cannot listen on 127.0.0.1:{port}" in r.stderr, r.stderr
    assert time.monotonic() - t0 < 15  # no cluster was started (that takes 30 s)


def _scene_folder(tmp_path: Path, size: int = 32) -> Path:
    import numpy as np

    from maxfs.storage.datasets import write_npy_folder
    from maxfs.worker import synthetic

    sc = synthetic.bump_scene(8, size, seed=1)
    return write_npy_folder(tmp_path / "in", sc.images.astype(np.uint8), sc.lights, sc.mask)


@pytest.mark.slow
def test_done_says_the_time_the_user_waited_and_the_solving_time(tmp_path: Path) -> None:
    folder = _scene_folder(tmp_path)
    t0 = time.monotonic()
    r = subprocess.run(
        [
            MAXFS,
            "run",
            str(folder),
            "-o",
            str(tmp_path / "out"),
            "--eps",
            "1",
            "--tile",
            "16",
            "--workers",
            "1",
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    waited = time.monotonic() - t0
    assert r.returncode == 0, r.stderr
    line = next(ln for ln in r.stdout.splitlines() if ln.startswith("done: "))
    said = float(line.split(" masked pixels in ", 1)[1].split(" s ", 1)[0])
    solving = float(line.split(" s (", 1)[1].split(" s solving)", 1)[0])
    assert solving <= said <= waited and said > waited - 1.5, (line, waited)
    assert "0/0 tiles" not in r.stderr


@pytest.mark.slow
def test_ctrl_c_in_the_first_seconds_prints_a_line_not_a_traceback(tmp_path: Path) -> None:
    import signal

    folder = _scene_folder(tmp_path, 64)
    for delay in (0.3, 1.5):
        p = subprocess.Popen(
            [MAXFS, "run", str(folder), "-o", str(tmp_path / f"out{delay}"), "--eps", "1", "--tile", "16"],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        time.sleep(delay)
        p.send_signal(signal.SIGINT)
        _, err = p.communicate(timeout=120)
        if p.returncode == 0:
            continue  # finished before the signal (a fast machine): nothing to check
        assert p.returncode == 130 and "Traceback" not in err, err
        assert "maxfs: interrupted" in err


# --- what the server's answers say -----------------------------------------------------------------
def test_jobs_show_their_name_and_progress_weighed_by_pixels() -> None:
    from maxfs.service.cli.verbs import format_status
    from maxfs.service.http.models import status_body
    from maxfs.storage.records import JobRecord, JobState

    rec = JobRecord(
        id="a" * 32,
        name="bear",
        state=JobState.RUNNING,
        tiles_total=4,
        tiles_done=1,
        pixels_total=1000,
        pixels_done=700,
    )
    body = status_body(rec, "http://x")
    assert body["name"] == "bear" and body["progress"]["fraction"] == 0.7
    assert format_status(body).startswith(f"{'a' * 32}  bear  running    tiles 1/4 (70%)")


def test_the_page_says_who_is_signed_in() -> None:
    from maxfs.service.http.routes import signed_in_as
    from maxfs.storage.tokens import User

    assert signed_in_as(User("alice"), auth=True) == "alice"
    assert signed_in_as(User("root", admin=True), auth=True) == "root (admin)"
    assert signed_in_as(User("local", admin=True), auth=False) == "no sign-in (auth is off)"
    js = (Path(__file__).parents[1] / "service" / "static" / "page" / "page.js").read_text()
    assert 'r.headers.get("X-Maxfs-User")' in js and '"Signed in as "' in js


def test_submit_shows_upload_progress_on_a_terminal() -> None:
    import io

    from maxfs.service.cli.verbs import UploadProgress

    class Terminal(io.StringIO):
        def isatty(self) -> bool:
            return True

    tty, log = Terminal(), io.StringIO()
    for stream in (tty, log):
        with UploadProgress(5, stream=stream) as shown:
            for i in range(1, 6):
                shown.update(i, 5)
    assert "uploading" in tty.getvalue() and "5/5" in tty.getvalue()
    assert log.getvalue() == ""  # off a terminal: no bar (the job id and --wait's lines follow)
