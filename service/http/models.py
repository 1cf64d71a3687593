"""Pydantic models of what the HTTP API takes (:class:`CreateJob`) and answers, and the status body.

The server declares these on its routes (``response_model=``, and through :mod:`service.http.openapi` for
errors), so ``/openapi.json``, ``/docs`` and ``/redoc`` describe the real bodies; the client
(:mod:`service.cli.client`) checks every answer against the same models. This module imports only pydantic
and the job states, so the command line's client stays quick to start.

A status body is the job record (:class:`storage.records.JobRecord`) plus ``progress``, ``warnings``,
``results`` and ``links``; fields added to the record later still pass through (``extra="allow"``),
so a model never drops what a client relies on. :func:`status_body` makes that body from a record.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, create_model, model_validator

from maxfs.storage.options import DTYPES, SOLVE_OPTIONS, Option
from maxfs.storage.records import JobState

if TYPE_CHECKING:
    from maxfs.storage.records import JobRecord

#: Header on result answers: "true" while the job is not done (unfinished tiles hold fill values).
PARTIAL_HEADER = "X-Maxfs-Partial"


def _open(schema: dict[str, Any]) -> None:
    # JSON Schema allows other properties unless told otherwise: saying so again only puts
    # "additionalProp1" into every example of the docs
    schema.pop("additionalProperties", None)


#: Bodies may carry fields added after this model: the client keeps them (``model_extra``).
OPEN = ConfigDict(extra="allow", json_schema_extra=_open)


class ErrorBody(BaseModel):
    """Every error answer: the error's class and what is wrong (and how to fix it)."""

    model_config = ConfigDict(
        json_schema_extra={"example": {"error": "NotFoundError", "detail": "no job 0f3c"}}
    )

    error: str = Field(description="class of the error, e.g. NotFoundError, ConflictError, AuthError")
    detail: str = Field(description="what is wrong, in words, and what to do about it")


class Progress(BaseModel):
    """How far a job is; shares are over all masked pixels (unfinished ones count as not solved)."""

    model_config = OPEN

    fraction: float = Field(
        description="masked pixels solved (in finished tiles, and so far in running ones) / masked "
        "pixels (tiles done / tiles total while the mask is not counted); 0 before the first start"
    )
    tiles_done: int
    tiles_total: int
    pixels_done: int = Field(description="masked pixels in finished tiles")
    pixels_running: int = Field(0, description="masked pixels solved so far in tiles still running")
    pixels_total: int = Field(description="masked pixels")
    pixels_per_second: float | None = Field(None, description="masked pixels per second in this run")
    eta_seconds: float | None = Field(None, description="seconds left at the current rate (running jobs)")
    solved_share: float | None = Field(
        None, description="share of all masked pixels with a normal (unfinished tiles count as not solved)"
    )
    certified_share: float | None = Field(
        None, description="share of all masked pixels whose optimum was proved"
    )


class ResultsInfo(BaseModel):
    """Whether results can be fetched, and whether they are partial."""

    model_config = OPEN

    available: bool = Field(description="false until the job is first started (results answer 409)")
    partial: bool = Field(description="true while the job is not done (unfinished tiles hold fill values)")
    note: str = Field("", description="what the results are, in words (the job page shows it)")
    resumable: bool = Field(
        True,
        description="false for a failed job: a resume with the same inputs and options fails the same way",
    )


class Links(BaseModel):
    model_config = OPEN

    self: str = Field(description="this job's status")
    start: str
    zip: str = Field(description="results.zip")


class JobStatus(BaseModel):
    """A job's record, progress, warnings and links (``GET /jobs/{id}``, and every job route's answer)."""

    model_config = OPEN

    id: str = Field(description="32 hexadecimal digits")
    state: JobState
    owner: str = Field(description="the user whose token created the job")
    name: str | None = Field(None, description="what people call the job (default: the folder's name)")
    created_at: float = Field(description="Unix time")
    updated_at: float
    started_at: float | None = Field(
        None, description="the latest start (or resume); null = never started (no results)"
    )
    finished_at: float | None = None
    error: str | None = Field(None, description="why a failed job failed")
    tiles_total: int = 0
    tiles_done: int = 0
    pixels_total: int = 0
    pixels_done: int = 0
    pixels_running: int = 0
    certified_pixels: int = 0
    solved_pixels: int = 0
    pixel_rate: float | None = None
    eps: float | None = Field(None, description="the eps used (known once eps=auto is estimated)")
    raw_step: int | None = Field(
        None,
        description="the step of the images' raw values, measured when the job starts: 1 for data "
        "using every value, 16 for 12-bit data shifted into 16-bit files, 257 for 8-bit data "
        "scaled to 16 bits; it sets the quantisation error and the saturation level",
    )
    progress: Progress
    warnings: list[str] = Field(default_factory=list, description="what a user must hear about the result")
    calibration: list[str] = Field(
        default_factory=list,
        description="why the lights, intensities or mask look wrong (also in warnings); a result with "
        "any is not to be trusted even where certified optimal",
    )
    results: ResultsInfo
    links: Links
    uploaded: int | list[int] | None = Field(
        None,
        description="single-job answers: how many images are uploaded (of k); job lists: the record's "
        "indices of the images stored before start",
    )
    k: int | None = Field(None, description="images the job needs (single-job answers)")
    status_url: str | None = Field(None, description="where to poll (the answer of start)")


class Health(BaseModel):
    status: str = Field(examples=["ok"])
    auth: bool = Field(description="whether /jobs routes need a bearer token")


#: ``POST /jobs`` fields that hold numbers (or lists of them), and those that hold true/false.
NUMBER_FIELDS = frozenset(
    {"k", "height", "width", "channels", "lights", "intensities"}
    | {o.name for o in SOLVE_OPTIONS if o.kind not in ("bool", "choice")}
)
FLAG_FIELDS = frozenset(o.name for o in SOLVE_OPTIONS if o.kind == "bool")


def _holds_bool(value: Any) -> bool:
    return isinstance(value, bool) or (isinstance(value, list) and any(_holds_bool(v) for v in value))


class JobShape(BaseModel):
    """The stack's shape and lights: the part of :class:`CreateJob` that is not a solve option."""

    model_config = ConfigDict(extra="forbid")

    @model_validator(mode="before")
    @classmethod
    def _true_is_no_number(cls, data: Any) -> Any:
        """JSON ``true`` is not the number 1, nor ``0`` a flag (pydantic's lax mode reads them so)."""
        if isinstance(data, dict):
            for name, value in data.items():
                if name in NUMBER_FIELDS and _holds_bool(value):
                    raise ValueError(f"{name}: a number, not true or false")
                if name in FLAG_FIELDS and value is not None and not isinstance(value, bool):
                    raise ValueError(f"{name}: true or false, got {value!r}")
        return data

    k: int = Field(description="number of images (at least 3)")
    height: int = Field(description="image height in pixels")
    width: int = Field(description="image width in pixels")
    channels: Literal[1, 3] = Field(1, description="1 = grey, 3 = RGB")
    dtype: Literal[DTYPES] = "uint8"  # type: ignore[valid-type]
    lights: list[list[float]] = Field(description="k unit light directions (x right, y up, z toward camera)")
    intensities: list[float] | list[list[float]] | None = Field(
        None, description="light intensities: k values, or k x channels"
    )
    name: str | None = Field(
        None,
        max_length=200,
        description="what people call the job (`maxfs submit` sends the folder's name, or --name)",
    )
    label: str | None = Field(
        None,
        max_length=200,
        description="your name for the submission; `maxfs submit` finds an unfinished job by it to resume",
    )


#: Pydantic types of the kinds of :class:`storage.options.Option`.
_KINDS: dict[str, Any] = {
    "float": float,
    "int": int,
    "bool": bool,
    "float|auto": float | Literal["auto"],
    "int|auto": int | Literal["auto"],
}


def _option_field(o: Option) -> tuple[Any, Any]:
    kind = Literal[o.choices] if o.kind == "choice" else _KINDS[o.kind]
    return (kind if o.default is not None else kind | None), Field(o.default, description=o.help)


#: ``POST /jobs``: a :class:`JobShape` plus one field per row of
#: :data:`storage.options.SOLVE_OPTIONS` (the CLI's flags come from the same rows). Only types
#: are checked here; values by the one validator the library and the CLI use too
#: (:meth:`JobSpec.validate`, :meth:`JobParams.build`). Unknown fields are refused, so a
#: misspelt option is never silently ignored.
CreateJob = create_model(
    "CreateJob",
    __base__=JobShape,
    __doc__="A new job: the stack's shape, the lights, and the solve options.",
    **{o.name: _option_field(o) for o in SOLVE_OPTIONS},
)


def solve_options(req: BaseModel) -> dict[str, Any]:
    """The solve options a :class:`CreateJob` gives, by name (unset ones left out)."""
    return {o.name: v for o in SOLVE_OPTIONS if (v := getattr(req, o.name)) is not None}


def results_note(rec: JobRecord) -> str:
    """What a job's results are, said on its page: never "not started" for a job that ran."""
    n, of = rec.tiles_done, rec.tiles_total
    if rec.state is JobState.DONE:
        return ""
    if rec.state is JobState.FAILED:
        got = f"partial results: {n} of {of} tiles finished" if n else "no results: no tile finished"
        return (
            f"The job failed ({got}); the error above says why. Resuming it with the same inputs and "
            "options would fail the same way, so submit it again with other options."
        )
    if rec.state is JobState.CANCELLED:
        if not n:
            return "No results: the job was cancelled before any tile finished."
        return f"Partial results: cancelled after {n} of {of} tiles; Resume goes on from there."
    if rec.state in (JobState.CREATED, JobState.UPLOADING):
        return "No results yet: the job has not been started."
    if not n:
        return f"No results yet: the job is {rec.state.value}."
    return f"Partial results: {n} of {of} tiles so far."


def status_body(
    rec: JobRecord, base: str, uploaded: int | None = None, k: int | None = None
) -> dict[str, Any]:
    """The JSON body of a job (:class:`JobStatus`): its record plus progress, warnings, results and
    links under ``base``; ``uploaded`` and ``k`` in single-job answers."""
    body = rec.to_json()
    body.pop("uploaded_images", None)  # the indices; "uploaded" (count) and "missing_images" say it
    frac = rec.tiles_done / rec.tiles_total if rec.tiles_total else 0.0
    if rec.pixels_total:  # a tile of the object's edge is less work than a full one
        # solved pixels of running tiles count too: one large tile does not sit at 0 % for minutes
        done = rec.pixels_done + (rec.pixels_running if rec.state.active else 0)
        frac = min(done / rec.pixels_total, 1.0) if rec.state is not JobState.DONE else 1.0
    body["progress"] = {
        "fraction": frac,
        "tiles_done": rec.tiles_done,
        "tiles_total": rec.tiles_total,
        "pixels_done": rec.pixels_done,
        "pixels_running": rec.pixels_running if rec.state.active else 0,
        "pixels_total": rec.pixels_total,
        "pixels_per_second": rec.pixel_rate,
        "eta_seconds": rec.eta_seconds,
        "solved_share": rec.solved_share,
        "certified_share": rec.certified_share,
    }
    body["warnings"] = rec.warnings()
    # results are complete only when done; before the first start there are none at all
    body["results"] = {
        "available": rec.started_at is not None,
        "partial": rec.state is not JobState.DONE,
        "note": results_note(rec),
        "resumable": rec.state is not JobState.FAILED,
    }
    if uploaded is not None:
        body["uploaded"] = uploaded
        body["k"] = k
    body["links"] = {
        "self": f"{base}/jobs/{rec.id}",
        "start": f"{base}/jobs/{rec.id}/start",
        "zip": f"{base}/jobs/{rec.id}/results.zip",
    }
    return body
