"""The ``maxfs`` script's entry point: a quiet Ctrl-C from the first instant.

Importing the command line (numpy, the settings) takes a moment; a Ctrl-C then would print a
traceback of the import. So the script's first code is this module, standard library only: it
answers SIGINT with one line and exit status 130 until :func:`maxfs.service.cli.main.console` is imported,
whose own handlers take over from there (same line, same status).

It also keeps the BLAS library to one thread, before numpy loads it (:func:`one_blas_thread`),
and makes the cyclic garbage collector's young generation larger
(:func:`maxfs.service.cli.gc_policy.fewer_collections`).
"""

from __future__ import annotations

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


def console() -> None:
    """Install the quiet handler, import the CLI, hand SIGINT back to Python, run it."""
    signal.signal(signal.SIGINT, _quiet)
    one_blas_thread()
    from maxfs.service.cli.gc_policy import fewer_collections  # standard library only

    fewer_collections()
    from maxfs.service.cli.main import console as run

    signal.signal(signal.SIGINT, signal.default_int_handler)
    run()
