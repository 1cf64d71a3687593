"""Test-only fault injection, so the product carries no test hooks.

Python imports ``sitecustomize`` at the start of every process that has this folder on its
``PYTHONPATH``: a server a test starts, and the Dask workers its embedded cluster spawns (they
inherit the environment). When ``MAXFS_TESTS_FAULTS`` (JSON, set by :func:`tests.faults.fault_env`)
names faults, this replaces the functions they need, before any maxfs code runs:

* ``fail_tiles``: a file path; while it exists, the tiles it lists ("8,9") raise in their task;
* ``free_bytes``: the server's file system reports this many bytes free;
* ``pause_mask_write``: a mask upload stops for a minute after its first band, with the store
  marked "mask being written", so a test can kill the server mid-write.
"""

from __future__ import annotations

import json
import os

_FAULTS = json.loads(os.environ.get("MAXFS_TESTS_FAULTS") or "{}")


def _install() -> None:
    import time
    from pathlib import Path

    import numpy as np

    if "fail_tiles" in _FAULTS:
        import maxfs.worker.task as task

        real_compute = task.compute_tile
        listing = Path(_FAULTS["fail_tiles"])

        def compute_tile(store, tile_index, *args, **kwargs):  # type: ignore[no-untyped-def]
            failing = listing.read_text() if listing.exists() else ""
            if str(tile_index) in failing.replace(" ", "").split(","):
                raise RuntimeError(f"tile {tile_index}: failure injected by the test (fail_tiles)")
            return real_compute(store, tile_index, *args, **kwargs)

        task.compute_tile = compute_tile

    if "free_bytes" in _FAULTS:
        from maxfs.service.http import guards

        free = int(_FAULTS["free_bytes"])
        guards.DiskBudget.free = lambda self: free  # type: ignore[method-assign]

    if _FAULTS.get("pause_mask_write"):
        from maxfs.storage.layout import MASK_WRITING, JobStore

        def write_mask(self, mask):  # type: ignore[no-untyped-def]
            self.group["inputs/input_digests"][self.spec.k] = np.frombuffer(MASK_WRITING, np.uint8)
            rows = int(self.group["mask"].chunks[0])
            self.group["mask"][0:rows] = np.asarray(mask, dtype=bool)[0:rows]
            time.sleep(60)

        JobStore.write_mask = write_mask  # type: ignore[method-assign]


if _FAULTS:
    _install()
