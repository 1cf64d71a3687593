"""The ``maxfs`` script's entry point: a quiet Ctrl-C from the first instant.

Importing the command line (numpy, the settings) takes a moment; a Ctrl-C then would print a
traceback of the import. So the script's first code is this module, standard library only: it
answers SIGINT with one line and exit status 130 until :func:`maxfs.service.cli.main.console` is imported,
whose own handlers take over from there (same line, same status).

It also keeps the BLAS library to one thread, before numpy loads it (:func:`one_blas_thread`),
and makes the cyclic garbage collector's young generation larger (:func:`fewer_collections`).
"""

from __future__ import annotations

import gc
import os
import signal
import sys


def _quiet(signum: int, frame: object) -> None:
    sys.stderr.write("\nmaxfs: interrupted\n")
    sys.stderr.flush()
    os._exit(130)


#: What :func:`one_blas_thread` sets, as Dask's nanny does for its workers.
BLAS_THREADS = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")


def one_blas_thread(env: dict[str, str] | os._Environ[str] = os.environ) -> None:
    """One BLAS thread unless the user set a count: the parallelism of a run is its tiles (on
    threads in process, on single-threaded Dask workers elsewhere), and the least-squares products
    are small, so a second BLAS thread only spins between them, on a core a tile needs (on 2
    cores it burned more CPU than the whole eps estimate computes)."""
    for name in BLAS_THREADS:
        env.setdefault(name, "1")


#: The young generation's threshold of :func:`fewer_collections` (CPython's default: 700).
GC_GEN0 = 20_000
#: The thresholds :func:`fewer_collections` replaced (None until it has run).
_USUAL: tuple[int, int, int] | None = None


def fewer_collections() -> None:
    """Collect the youngest generation after ``GC_GEN0`` net allocations instead of 700.

    A run imports numba, zarr and numpy: a few hundred thousand objects, none of them garbage.
    With the default threshold ``maxfs run`` collected about 350 times, twice the whole heap,
    0.1-0.25 s of a 3-4 s command spent walking live objects (measured with ``gc.callbacks`` on
    bench.phases's capture); with 20,000 it collects about 10 times and never the whole heap.
    Cycles still go: later, in batches, and a CLI process is short-lived; ``maxfs serve``, which is
    not, puts CPython's threshold back (:func:`usual_collections`)."""
    global _USUAL
    if _USUAL is None:  # a second call must not take this threshold for CPython's
        _USUAL = gc.get_threshold()
    gc.set_threshold(GC_GEN0, _USUAL[1], _USUAL[2])


def usual_collections() -> None:
    """The thresholds :func:`fewer_collections` replaced, for a long-running process (the server):
    there a request's garbage cycles may hold an upload's buffers, and should go soon."""
    if _USUAL is not None:
        gc.set_threshold(*_USUAL)


def console() -> None:
    """Install the quiet handler, import the CLI, hand SIGINT back to Python, run it."""
    signal.signal(signal.SIGINT, _quiet)
    one_blas_thread()
    fewer_collections()
    from maxfs.service.cli.main import console as run

    signal.signal(signal.SIGINT, signal.default_int_handler)
    run()
