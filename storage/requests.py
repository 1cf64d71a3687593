"""A job from what a user asked: the one builder the CLI, HTTP and the Python API share.

The user gives a stack's shape (:class:`~maxfs.storage.layout.JobSpec`) and solve options by
name (:data:`~maxfs.storage.options.SOLVE_OPTIONS`); unset options take the rows' defaults, the
tile edge is resolved ("auto" or checked by hand), and :meth:`JobParams.build` validates the rest.
Validation happens here, once per job, never per tile.
"""

from __future__ import annotations

import difflib
from collections.abc import Mapping
from typing import Any

import numpy as np
from numpy.typing import NDArray

from maxfs.storage.errors import InvalidInputError
from maxfs.storage.options import SOLVE_OPTIONS
from maxfs.storage.params import ESTIMATE_MIN_IMAGES, JobParams, check_tile_edge
from maxfs.storage.spec import JobSpec
from maxfs.storage.tiles import WORK_COST, WORK_PER_TILE

#: Option names a request may give.
OPTION_NAMES: tuple[str, ...] = tuple(o.name for o in SOLVE_OPTIONS)
#: What an unset option means to a user (only the options whose default is not the model's).
DEFAULTS: dict[str, Any] = {o.name: o.default for o in SOLVE_OPTIONS if o.default is not None}


def check_names(options: Mapping[str, Any]) -> None:
    """Refuse an option name that does not exist, suggesting the closest one."""
    for name in options:
        if name not in OPTION_NAMES:
            close = difflib.get_close_matches(name, OPTION_NAMES, n=1)
            hint = f"; did you mean {close[0]!r}?" if close else ""
            raise InvalidInputError(f"unknown option {name!r}{hint} (options: {', '.join(OPTION_NAMES)})")


def resolve_tile(
    spec: JobSpec, tile: int | str, solver: str, task_memory: int, mask: NDArray[np.bool_] | None = None
) -> int:
    """The tile edge of a new job: "auto", or one given by hand, which must fit the task memory
    (:meth:`JobSpec.check_tile`) and the work per task that "auto" keeps to:
    ``tile**2 * k * WORK_COST[solver]`` at most :data:`storage.tiles.WORK_PER_TILE` (the MILP's
    cost is 16: about a hundred times slower per pixel), so one task lasts seconds. ``mask``: the
    job's mask where it is known before the job is made (a local run, not an HTTP submit, whose
    mask comes after): "auto" then also balances the masked pixels over the tiles."""
    if tile != "auto":
        check_tile_edge(tile)
    edge = spec.resolve_tile(tile, task_memory, solver, mask)
    if tile != "auto":
        cost = WORK_COST.get(str(solver), 1)
        work = edge * edge * spec.k * cost
        if work > WORK_PER_TILE:
            fit = max(int((WORK_PER_TILE / (spec.k * cost)) ** 0.5) // 8 * 8, 8)
            raise InvalidInputError(
                f"tile {edge} means {edge * edge} pixels x {spec.k} images per task"
                f"{' with the MILP' if cost > 1 else ''}, more work than one task may have "
                f"({WORK_PER_TILE // cost} pixel-images); use tile {fit} or less, or 'auto'"
            )
    return edge


def tile_is_auto(options: Mapping[str, Any]) -> bool:
    """Whether ``options`` leave the tile edge to "auto" (given so, or not given)."""
    tile = options.get("tile")
    return str(DEFAULTS["tile"] if tile is None else tile) == "auto"


def job_params(
    spec: JobSpec, options: Mapping[str, Any], task_memory: int, mask: NDArray[np.bool_] | None = None
) -> JobParams:
    """Validated parameters of a job on ``spec`` from the options a user gave (None = unset);
    ``mask`` as for :func:`resolve_tile`."""
    check_names(options)
    opts = DEFAULTS | {k: v for k, v in options.items() if v is not None}
    tile = resolve_tile(spec, opts["tile"], str(opts["solver"]), task_memory, mask)
    params = JobParams.build(**opts | {"tile": tile})
    if params.eps_request == "auto" and spec.k < ESTIMATE_MIN_IMAGES:
        # refused here, before anything is stored, rather than by the estimate once the job runs
        raise InvalidInputError(
            f"{spec.k} images are too few to estimate eps (that needs {ESTIMATE_MIN_IMAGES} usable "
            "images per pixel): give it (maxfs run --eps E, or the job's field eps), E about three "
            "times the noise standard deviation in grey levels: e.g. 3 for clean 8-bit images, "
            "about 770 (3 x 257) for 16-bit ones"
        )
    return params
