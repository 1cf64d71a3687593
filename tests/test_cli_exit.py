"""``maxfs`` ends without the interpreter's teardown once its work is done
(:func:`service.cli.main.console`), also when thread pools still hold idle threads."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

SCRIPT = textwrap.dedent(
    """
    import atexit, sys, threading, time
    from concurrent.futures import ThreadPoolExecutor
    from pathlib import Path
    import maxfs.service.cli.main as cli

    out = Path(sys.argv[1])

    class Torn:  # its __del__ runs in the interpreter's teardown, never after os._exit
        def __del__(self):
            print("teardown", flush=True)

    kept = Torn()
    pool = ThreadPoolExecutor(2)

    def main():
        pool.submit(lambda: None).result()  # an idle pool thread stays, as Dask's offload thread does
        if sys.argv[2] == "running":  # a pool task still at work when main returns: waited for
            pool.submit(lambda: (time.sleep(0.3), (out / "task").write_text("done")))
        if sys.argv[2] == "thread":  # a plain thread at work: Python exits as usual
            threading.Thread(target=lambda: time.sleep(0.3)).start()
        return 3

    atexit.register(lambda: print("atexit", flush=True))
    cli.main = main
    cli.console()
    """
)


def run(tmp_path: Path, case: str) -> subprocess.CompletedProcess:
    script = tmp_path / "exit.py"
    script.write_text(SCRIPT)
    return subprocess.run(
        [sys.executable, str(script), str(tmp_path), case], capture_output=True, text=True, timeout=60
    )


def test_idle_pool_threads_do_not_keep_the_teardown(tmp_path: Path) -> None:
    r = run(tmp_path, "idle")
    assert r.returncode == 3, r.stderr
    assert r.stdout.split() == ["atexit"]


def test_a_pool_task_still_running_is_waited_for(tmp_path: Path) -> None:
    r = run(tmp_path, "running")
    assert r.returncode == 3, r.stderr
    assert (tmp_path / "task").read_text() == "done"
    assert r.stdout.split() == ["atexit"]


def test_a_thread_at_work_gets_the_usual_exit(tmp_path: Path) -> None:
    r = run(tmp_path, "thread")
    assert r.returncode == 3, r.stderr
    assert r.stdout.split() == ["atexit", "teardown"]
