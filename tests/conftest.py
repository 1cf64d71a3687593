"""The test harness as fixtures.

Processes (each killed at teardown, however the test ended; see :class:`tests.procs.Procs`):

* ``procs`` / ``module_procs``: start what a test (a module) needs; killed after it.
* ``dask_cluster`` / ``module_dask_cluster``: ``dask scheduler`` and two single-threaded
  ``dask worker`` processes on loopback.
* ``server_factory`` / ``module_server_factory``: ``maxfs serve`` on a free loopback port,
  ``factory(data_dir=None, scheduler="", *, workers=1, auth=False, env=None, port=None)``
  (``scheduler=""``: the server's embedded cluster).
* ``inprocess_server``: the app under uvicorn in a thread of this process.

Data:

* ``scene``: ``scene("bump" | "sphere", k, size, **kw)``, synthetic scenes made once per session
  (read-only arrays: copy before changing one).
* ``uw_psm``, ``diligent``: the real datasets in ``../shared/data`` (skip, naming it, when absent;
  ``.ci/run`` requires them).
* ``reference_solution``: the in-process solve of a scene, by default the HiGHS MILP with the HTTP
  default model ("robust"), computed once per module for each scene and parameters.

Waiting: :func:`tests.procs.poll_until` (the one polling helper).

Tiers (as dask/distributed does): a test that uses a process fixture, or is marked ``slurm`` or
``browser``, is marked ``slow`` here, unless it is marked ``smoke``: the few real-process tests the
fast tier keeps so that it still covers every layer for real (one server, one Dask job, one browser
check). The README's command runs ``-m "not slow"``; ``bash .ci/run`` runs everything.
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from maxfs.worker import synthetic
from maxfs.worker.solve import Solution, solve
from tests import data
from tests.procs import DaskCluster, InProcessServer, Procs, Server, log_tails

# -- processes ---------------------------------------------------------------------------------

#: Fixtures that start real processes (servers, schedulers, workers).
PROCESS_FIXTURES = frozenset(
    {
        "procs",
        "module_procs",
        "dask_cluster",
        "module_dask_cluster",
        "server_factory",
        "module_server_factory",
        "inprocess_server",
    }
)


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    for item in items:
        if item.get_closest_marker("smoke"):
            continue
        names = set(getattr(item, "fixturenames", ()))
        if "chrome" in names:
            item.add_marker(pytest.mark.browser)
        heavy = PROCESS_FIXTURES & names
        if heavy or item.get_closest_marker("slurm") or item.get_closest_marker("browser"):
            item.add_marker(pytest.mark.slow)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo) -> Iterator[None]:
    """A failing test's report ends with the tails of the server, scheduler and worker logs
    of what is running (CI keeps only what pytest prints)."""
    outcome = yield
    report = outcome.get_result()
    if report.failed and call.when in ("setup", "call"):
        for path, tail in log_tails():
            report.sections.append((f"log {path}", tail))


@pytest.fixture
def procs(tmp_path: Path) -> Iterator[Procs]:
    p = Procs(tmp_path)
    try:
        yield p
    finally:
        p.close()


@pytest.fixture(scope="module")
def module_procs(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Procs]:
    p = Procs(tmp_path_factory.mktemp("procs"))
    try:
        yield p
    finally:
        p.close()


@pytest.fixture
def dask_cluster(procs: Procs) -> DaskCluster:
    return procs.cluster(n_workers=2)


@pytest.fixture(scope="module")
def module_dask_cluster(module_procs: Procs, tmp_path_factory: pytest.TempPathFactory) -> DaskCluster:
    return module_procs.cluster(n_workers=2, logs=tmp_path_factory.mktemp("dask"))


@pytest.fixture
def server_factory(procs: Procs) -> Callable[..., Server]:
    return procs.server


@pytest.fixture(scope="module")
def module_server_factory(module_procs: Procs) -> Callable[..., Server]:
    return module_procs.server


@pytest.fixture
def inprocess_server(procs: Procs) -> Callable[[Any], InProcessServer]:
    return procs.inprocess


# -- data --------------------------------------------------------------------------------------


def _frozen(sc: synthetic.Scene) -> synthetic.Scene:
    for v in vars(sc).values():
        if isinstance(v, np.ndarray):
            v.flags.writeable = False
    return sc


@pytest.fixture(scope="session")
def scene() -> Callable[..., synthetic.Scene]:
    made: dict[tuple, synthetic.Scene] = {}
    makers = {"bump": synthetic.bump_scene, "sphere": synthetic.sphere}

    def make(kind: str, k: int, size: int, **kw: Any) -> synthetic.Scene:
        key = (kind, k, size, tuple(sorted(kw.items())))
        if key not in made:
            made[key] = _frozen(makers[kind](k, size, **kw))
        return made[key]

    return make


@pytest.fixture(scope="session")
def uw_psm() -> Path:
    """``../shared/data/uw-psm`` (one folder per object in :data:`tests.data.UW_OBJECTS`)."""
    return data.require(data.UW, "lights.txt")


@pytest.fixture(scope="session")
def diligent() -> Path:
    """``../shared/data/diligent-crop8`` (catPNG, cowPNG, pot1PNG)."""
    return data.require(data.DILIGENT)


def _digest(*arrays: np.ndarray | None) -> str:
    h = hashlib.sha256()
    for a in arrays:
        if a is None:
            h.update(b"none")
        else:
            a = np.ascontiguousarray(a)
            h.update(f"{a.dtype}{a.shape}".encode())
            h.update(a.tobytes())
    return h.hexdigest()


@pytest.fixture(scope="module")
def reference_solution() -> Callable[..., Solution]:
    """``ref(images, lights, mask=None, **params)``: :func:`worker.solve.solve` with
    ``solver="milp"`` and ``model="robust"`` unless ``params`` say otherwise; each distinct
    call is solved once per module."""
    solved: dict[tuple, Solution] = {}

    def ref(
        images: np.ndarray, lights: np.ndarray, mask: np.ndarray | None = None, **params: Any
    ) -> Solution:
        params = {"solver": "milp", "model": "robust", **params}
        key = (_digest(images, lights, mask), tuple(sorted(params.items())))
        if key not in solved:
            solved[key] = solve(images, lights, mask, **params)
        return solved[key]

    return ref
