"""Job parameters and their hash: what makes a finished tile reusable."""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, dataclass, replace
from typing import Any

from worker.errors import InvalidInputError
from worker.problem import DEFAULT_BOX_FACTOR, check_options
from worker.solve import DEFAULT_MAX_NODES, DEFAULT_MILP_TIME_LIMIT, Solver
from worker.tiles import DEFAULT_TILE


@dataclass(frozen=True)
class JobParams:
    """Everything that changes a tile's result.

    ``eps`` is the number used; ``eps_request`` is what the user asked for
    (a number, or ``"auto"``, resolved before any tile runs).
    """

    solver: str = Solver.EXACT.value
    eps: float | None = 1.0
    eps_request: float | str = 1.0
    shadow: float | None = None
    saturation: float | None = None
    box_factor: float = DEFAULT_BOX_FACTOR
    tile: int = DEFAULT_TILE
    max_nodes: int = DEFAULT_MAX_NODES
    milp_time_limit: float = DEFAULT_MILP_TIME_LIMIT

    @classmethod
    def build(
        cls,
        *,
        eps: float | str = 1.0,
        solver: str = "exact",
        tile: int = DEFAULT_TILE,
        shadow: float | None = None,
        saturation: float | None = None,
        box_factor: float = DEFAULT_BOX_FACTOR,
        max_nodes: int = DEFAULT_MAX_NODES,
        milp_time_limit: float = DEFAULT_MILP_TIME_LIMIT,
    ) -> JobParams:
        """Validate user-facing parameters (:func:`worker.problem.check_options`, the one
        validator the library, the CLI and HTTP share) and build them."""
        try:
            solver = Solver(solver).value
        except ValueError:
            raise InvalidInputError(
                f"unknown solver {solver!r}; choose one of {', '.join(s.value for s in Solver)}"
            ) from None
        if isinstance(eps, str) and eps != "auto":
            try:
                eps = float(eps)
            except ValueError:
                raise InvalidInputError(f"eps must be a positive number or 'auto', got {eps!r}") from None
        if isinstance(tile, bool) or not isinstance(tile, int) or not 8 <= tile <= 4096:
            raise InvalidInputError(f"tile must be a whole number between 8 and 4096 pixels, got {tile!r}")
        check_options(
            eps=None if eps == "auto" else eps,
            shadow=shadow,
            saturation=saturation,
            box_factor=box_factor,
            max_nodes=max_nodes,
            milp_time_limit=milp_time_limit,
        )
        return cls(
            solver=solver,
            eps=None if eps == "auto" else float(eps),
            eps_request=eps if eps == "auto" else float(eps),
            shadow=None if shadow is None else float(shadow),
            saturation=None if saturation is None else float(saturation),
            box_factor=float(box_factor),
            tile=int(tile),
            max_nodes=int(max_nodes),
            milp_time_limit=float(milp_time_limit),
        )

    def with_eps(self, eps: float) -> JobParams:
        return replace(self, eps=float(eps))

    def to_json(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> JobParams:
        return cls(**d)

    def digest(self) -> str:
        """Hash of the parameters that change results (needs a resolved eps)."""
        if self.eps is None:
            raise InvalidInputError("eps is not resolved yet")
        blob = json.dumps(self.to_json(), sort_keys=True).encode()
        return hashlib.sha256(blob).hexdigest()[:16]

    def token(self) -> int:
        """A nonzero int32 derived from :meth:`digest`: the value of a done marker."""
        return int(self.digest()[:8], 16) % (2**31 - 1) + 1
