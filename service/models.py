"""Pydantic models of what the HTTP API answers.

The server declares these on its routes (``response_model=``, and through :mod:`service.openapi` for
errors), so ``/openapi.json``, ``/docs`` and ``/redoc`` describe the real bodies; the client
(:mod:`service.client`) checks every answer against the same models. This module imports only pydantic
and the job states, so the command line's client stays quick to start.

A status body is the job record (:class:`storage.records.JobRecord`) plus ``progress``, ``warnings``,
``results`` and ``links``; fields added to the record later still pass through (``extra="allow"``),
so a model never drops what a client relies on.
"""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ConfigDict, Field

from storage.records import JobState


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
    """How far a job is; shares are over the masked pixels of the finished tiles."""

    model_config = OPEN

    fraction: float = Field(description="tiles done / tiles total (0 before the first start)")
    tiles_done: int
    tiles_total: int
    pixels_done: int = Field(description="masked pixels in finished tiles")
    pixels_total: int = Field(description="masked pixels")
    pixels_per_second: float | None = Field(None, description="masked pixels per second in this run")
    eta_seconds: float | None = Field(None, description="seconds left at the current rate (running jobs)")
    solved_share: float | None = Field(None, description="share of finished masked pixels with a normal")
    certified_share: float | None = Field(
        None, description="share of finished masked pixels whose optimum was proved"
    )


class ResultsInfo(BaseModel):
    """Whether results can be fetched, and whether they are partial."""

    model_config = OPEN

    available: bool = Field(description="false until the job is first started (results answer 409)")
    partial: bool = Field(description="true while the job is not done (unfinished tiles hold fill values)")


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
    created_at: float = Field(description="Unix time")
    updated_at: float
    started_at: float | None = Field(None, description="first start; null = never started (no results)")
    finished_at: float | None = None
    error: str | None = Field(None, description="why a failed job failed")
    tiles_total: int = 0
    tiles_done: int = 0
    pixels_total: int = 0
    pixels_done: int = 0
    certified_pixels: int = 0
    solved_pixels: int = 0
    pixel_rate: float | None = None
    eps: float | None = Field(None, description="the eps used (known once eps=auto is estimated)")
    progress: Progress
    warnings: list[str] = Field(default_factory=list, description="what a user must hear about the result")
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
