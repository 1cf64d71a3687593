"""When the cyclic garbage collector runs in a ``maxfs`` process: a short command's policy and a
server's. Standard library only (the script's entry point installs it before anything loads).
"""

from __future__ import annotations

import gc

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
