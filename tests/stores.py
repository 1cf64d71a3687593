"""Job stores brought to a given state for the tests, as a run would leave them."""

from __future__ import annotations

import numpy as np

from maxfs.service.runs.progress import resolve_eps
from maxfs.storage.datasets import Dataset
from maxfs.storage.layout import JobStore
from maxfs.worker.problem import make_thresholds
from maxfs.worker.solve import solve_tile
from maxfs.worker.task import estimate_eps_of


def finish_a_tile(store: JobStore, ds: Dataset) -> None:
    """Resolve the job's parameters, solve one tile that holds masked pixels and store it, as a
    run does (least squares: no compile); the store then holds a result worth keeping."""
    if not store.params.resolved:
        resolve_eps(
            store,
            estimate_eps_of(
                store, lambda t: np.stack([ds.read(i)[t.y0 : t.y1, t.x0 : t.x1] for i in range(ds.k)])
            ),
        )
    mask = store.read_mask()
    t = next(t for t in store.tiles() if mask[t.y0 : t.y1, t.x0 : t.x1].any())
    win = (slice(t.y0, t.y1), slice(t.x0, t.x1))
    raw = np.stack([ds.read(i)[win] for i in range(ds.k)])
    res = solve_tile(raw, ds.lights, store.observation_model, make_thresholds(ds.k, 1.0), "l2", mask[win])
    n = int(mask[win].sum())
    store.write_tile(t, res.outputs(), store.params.token(), (n, n, 0))
    assert store.progress().tiles_done == 1
