"""Job parameters and their hash: what makes a finished tile reusable."""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, dataclass, replace
from typing import Any

from maxfs.storage.errors import InvalidInputError
from maxfs.storage.options import (
    DEFAULT_BOX_FACTOR,
    DEFAULT_DEPTH_K,
    DEFAULT_MAX_NODES,
    DEFAULT_MILP_TIME_LIMIT,
    MODEL_DEFAULTS,
    DepthMethod,
    Estimate,
    Model,
    Solver,
    check_depth_options,
    check_options,
)
from maxfs.storage.tiles import DEFAULT_TILE

#: The tile edges a job may have, in pixels.
TILE_RANGE = (8, 4096)


def check_tile_edge(tile: object) -> None:
    """Refuse a tile edge that is not a whole number in :data:`TILE_RANGE` (before any arithmetic
    with it: a Python int may be far beyond a float's range)."""
    lo, hi = TILE_RANGE
    if isinstance(tile, bool) or not isinstance(tile, int) or not lo <= tile <= hi:
        raise InvalidInputError(f"tile must be a whole number between {lo} and {hi} pixels, got {tile!r}")


#: Usable images a pixel needs to take part in the eps estimate (:mod:`worker.noise`; 6 for
#: its trimmed fit, else least squares from 4): a job with fewer images must give eps.
ESTIMATE_MIN_IMAGES = 4


#: Fields that record what was asked for, not what was used: left out of :meth:`JobParams.digest`.
REQUEST_FIELDS = frozenset({"eps_request", "response_request"})
#: Options of the depth made after the run: they change no tile, so they are left out of the digest too
#: (a store made before they existed keeps its done tiles).
DEPTH_FIELDS = frozenset({"depth", "depth_k", "fx", "fy", "cx", "cy", "distance"})


@dataclass(frozen=True)
class JobParams:
    """Everything that changes a tile's result.

    ``eps`` is the number used; ``eps_request`` is what the user asked for
    (a number, or ``"auto"``, resolved before any tile runs). ``response`` and
    ``response_request`` likewise; both are resolved together, so ``eps`` is None
    until everything ``"auto"`` is (see :meth:`with_eps`). ``quantum``, the raw values'
    step (:func:`storage.observations.raw_quantum`), is measured on the data when the job
    starts, whatever was asked: None until then; 1 in records made before it existed, which
    is what they used. The job is :attr:`resolved` when both are known. The model's options
    (``model`` and the five after it) are stored resolved: the defaults of
    :data:`worker.problem.MODEL_DEFAULTS` are filled in by :meth:`build`.
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
    model: str = Model.PAPER.value
    response: float | None = 1.0
    response_request: float | str = 1.0
    eps_rel: float = 0.0
    drop_bright: float = 0.0
    dequantize: bool = False
    fallback: bool = False
    quantum: int | None = 1
    depth: str = DepthMethod.LS.value
    depth_k: float = DEFAULT_DEPTH_K
    fx: float | None = None
    fy: float | None = None
    cx: float | None = None
    cy: float | None = None
    distance: float | None = None

    @classmethod
    def build(
        cls,
        *,
        eps: float | str = 1.0,
        solver: str = "exact",
        tile: int = DEFAULT_TILE,
        shadow: float | None = None,
        saturation: float | None = None,
        box_factor: float | None = None,
        max_nodes: int | None = None,
        milp_time_limit: float | None = None,
        model: str = Model.PAPER.value,
        response: float | str | None = None,
        eps_rel: float | None = None,
        drop_bright: float | None = None,
        dequantize: bool | None = None,
        fallback: bool | None = None,
        depth: str | None = None,
        depth_k: float | None = None,
        fx: float | None = None,
        fy: float | None = None,
        cx: float | None = None,
        cy: float | None = None,
        distance: float | None = None,
    ) -> JobParams:
        """Validate user-facing parameters (:func:`storage.options.check_options`, the one
        validator the library, the CLI and HTTP share) and build them. The keywords are the
        names of :data:`storage.options.SOLVE_OPTIONS`; None means the default."""
        box_factor = DEFAULT_BOX_FACTOR if box_factor is None else box_factor
        max_nodes = DEFAULT_MAX_NODES if max_nodes is None else max_nodes
        milp_time_limit = DEFAULT_MILP_TIME_LIMIT if milp_time_limit is None else milp_time_limit
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
        check_tile_edge(tile)
        check_options(
            eps=None if eps == "auto" else eps,
            shadow=shadow,
            saturation=saturation,
            box_factor=box_factor,
            max_nodes=max_nodes,
            milp_time_limit=milp_time_limit,
            model=model,
            eps_rel=eps_rel,
            response=response,
            drop_bright=drop_bright,
        )
        depth = DepthMethod.LS.value if depth is None else depth
        depth_k = DEFAULT_DEPTH_K if depth_k is None else depth_k
        check_depth_options(depth=depth, depth_k=depth_k, fx=fx, fy=fy, cx=cx, cy=cy, distance=distance)
        for name, flag in (("dequantize", dequantize), ("fallback", fallback)):
            if flag is not None and not isinstance(flag, bool):
                raise InvalidInputError(f"{name} must be true or false, got {flag!r}")
        d = MODEL_DEFAULTS[Model(model)]
        resp = d.response if response is None else response
        resp = resp if resp == "auto" else float(resp)
        unresolved = eps == "auto" or resp == "auto"
        return cls(
            solver=solver,
            eps=None if unresolved else float(eps),
            eps_request=eps if eps == "auto" else float(eps),
            shadow=None if shadow is None else float(shadow),
            saturation=None if saturation is None else float(saturation),
            box_factor=float(box_factor),
            tile=int(tile),
            max_nodes=int(max_nodes),
            milp_time_limit=float(milp_time_limit),
            model=Model(model).value,
            response=None if resp == "auto" else resp,
            response_request=resp,
            eps_rel=float(d.eps_rel if eps_rel is None else eps_rel),
            drop_bright=float(d.drop_bright if drop_bright is None else drop_bright),
            dequantize=bool(d.dequantize if dequantize is None else dequantize),
            fallback=bool(d.fallback if fallback is None else fallback),
            quantum=None,
            depth=str(depth),
            depth_k=float(depth_k),
            **{
                n: None if v is None else float(v)
                for n, v in (("fx", fx), ("fy", fy), ("cx", cx), ("cy", cy))
            },
            distance=None if distance is None else float(distance),
        )

    @property
    def resolved(self) -> bool:
        """Whether everything measured when the job starts is known (eps, response, quantum):
        only then do the parameters have a :meth:`digest` and tiles run."""
        return self.eps is not None and self.quantum is not None

    def with_eps(self, eps: float | Estimate) -> JobParams:
        """Resolved parameters: an :class:`~worker.noise.Estimate` sets eps, the response and
        the raw step; a number sets eps (the response must not be ``"auto"`` then) and takes
        the raw values as they are (step 1) where the step is not known yet."""
        if isinstance(eps, Estimate):
            return replace(self, eps=float(eps.eps), response=float(eps.response), quantum=int(eps.quantum))
        if self.response is None and self.response_request == "auto":
            raise InvalidInputError("the response is 'auto': resolve it with an Estimate")
        resp = self.response if self.response is not None else float(self.response_request)
        return replace(
            self, eps=float(eps), response=resp, quantum=1 if self.quantum is None else self.quantum
        )

    def unresolved(self) -> JobParams:
        """These parameters as :meth:`build` made them, before anything ``"auto"`` was resolved
        and the raw step measured."""
        auto = self.eps_request == "auto" or self.response_request == "auto"
        return replace(
            self,
            eps=None if auto else self.eps,
            response=None if self.response_request == "auto" else self.response,
            quantum=None,
        )

    def threshold_options(self) -> dict[str, Any]:
        """The model options of :func:`worker.problem.make_thresholds` (resolved response)."""
        return {
            "model": self.model,
            "eps_rel": self.eps_rel,
            "response": 1.0 if self.response is None else self.response,
            "drop_bright": self.drop_bright,
            "fallback": self.fallback,
        }

    def depth_options(self) -> dict[str, Any]:
        """The keywords of :func:`service.research.write_depth` these parameters ask for."""
        return {n: getattr(self, n) for n in sorted(DEPTH_FIELDS)}

    def to_json(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> JobParams:
        return cls(**d)

    def digest(self) -> str:
        """Hash of the parameters that change results (needs a resolved eps): every field
        but what the user asked for (:data:`REQUEST_FIELDS`) and the depth's (:data:`DEPTH_FIELDS`),
        since a resolved eps of 7.0 gives the same tiles whether it was asked for or estimated. A raw
        step of 1 is left out too: records made before it existed keep their finished tiles."""
        if not self.resolved:
            raise InvalidInputError("eps and the raw step are not resolved yet")
        fields = {k: v for k, v in self.to_json().items() if k not in REQUEST_FIELDS | DEPTH_FIELDS}
        if fields["quantum"] == 1:
            del fields["quantum"]
        blob = json.dumps(fields, sort_keys=True).encode()
        return hashlib.sha256(blob).hexdigest()[:16]

    def token(self) -> int:
        """A nonzero int32 derived from :meth:`digest`: the value of a done marker."""
        return int(self.digest()[:8], 16) % (2**31 - 1) + 1
