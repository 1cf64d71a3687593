"""Job records: the state a job is in, kept as a small JSON file per job.

The Dask scheduler keeps nothing across restarts; these records (and the done
markers in the Zarr store) are the truth. Writes are atomic (temp file + rename).
"""

from __future__ import annotations

import json
import os
import tempfile
import time
from dataclasses import asdict, dataclass, field
from enum import StrEnum
from pathlib import Path
from typing import Any

from maxfs.storage.errors import ConflictError, StoreError

RECORD_NAME = "maxfs-job.json"
#: Below this share of solved masked pixels a result comes with a loud warning.
LOW_SOLVED_SHARE = 0.5


class JobState(StrEnum):
    """Life cycle of a job."""

    CREATED = "created"  #: metadata stored, no image uploaded yet
    UPLOADING = "uploading"  #: some images uploaded, not all
    QUEUED = "queued"  #: started; waiting for workers (or eps estimation)
    RUNNING = "running"  #: tiles are being computed
    DONE = "done"  #: every tile finished; results complete
    FAILED = "failed"  #: stopped by an error; ``error`` says why
    CANCELLED = "cancelled"  #: stopped by the user; start again to resume

    @property
    def active(self) -> bool:
        return self in (JobState.QUEUED, JobState.RUNNING)

    @property
    def final(self) -> bool:
        """Nothing runs and nothing will, until the user starts it again."""
        return self in (JobState.DONE, JobState.FAILED, JobState.CANCELLED)

    @property
    def accepts_uploads(self) -> bool:
        return self in (JobState.CREATED, JobState.UPLOADING)

    def after(self, event: str) -> JobState:
        """The state an ``event`` leads to from this one (:data:`TRANSITIONS`); a
        :class:`ConflictError` naming both when the table has no such move."""
        try:
            return TRANSITIONS[event][self]
        except KeyError:
            if event not in TRANSITIONS:
                raise ValueError(f"unknown job event {event!r}") from None
            raise ConflictError(f"{EVENT_WORDS[event]} is not possible: the job is {self.value}") from None


#: States in which nothing runs and nothing will until the user starts the job again.
FINAL_STATES = frozenset(s for s in JobState if s.final)

_S = JobState
#: Every change of a job's state: event -> {state before: state after}. A move that is not
#: here is refused (409). The server applies them under the job's lock (service.http.jobs), so
#: two requests on one job (an upload and a cancel, a start and a cancel) happen one after
#: the other, each on the state the other left.
TRANSITIONS: dict[str, dict[JobState, JobState]] = {
    "upload": {_S.CREATED: _S.UPLOADING, _S.UPLOADING: _S.UPLOADING},  # an image
    "mask": {_S.CREATED: _S.CREATED, _S.UPLOADING: _S.UPLOADING},
    "start": {_S.CREATED: _S.QUEUED, _S.UPLOADING: _S.QUEUED, _S.FAILED: _S.QUEUED, _S.CANCELLED: _S.QUEUED},
    "resume": {_S.QUEUED: _S.QUEUED, _S.RUNNING: _S.QUEUED},  # the server restarted mid-run
    "run": {_S.QUEUED: _S.RUNNING},
    "finish": {_S.RUNNING: _S.DONE},
    "fail": {_S.QUEUED: _S.FAILED, _S.RUNNING: _S.FAILED},
    "cancel": {s: _S.CANCELLED for s in (_S.CREATED, _S.UPLOADING, _S.QUEUED, _S.RUNNING)},
    # delete (purge): only a job nothing runs for; its folder goes, so there is no state after
    "delete": {s: s for s in (_S.CREATED, _S.UPLOADING, _S.DONE, _S.FAILED, _S.CANCELLED)},
}
EVENT_WORDS = {
    "upload": "uploading an image",
    "mask": "setting the mask",
    "start": "starting",
    "resume": "resuming",
    "run": "running",
    "finish": "finishing",
    "fail": "failing",
    "cancel": "cancelling",
    "delete": "deleting",
}


@dataclass
class JobRecord:
    """Mutable facts about a job, owned by the process that runs it."""

    id: str
    state: JobState = JobState.CREATED
    owner: str = "local"
    created_at: float = field(default_factory=time.time)
    updated_at: float = field(default_factory=time.time)
    started_at: float | None = None
    finished_at: float | None = None
    error: str | None = None
    tiles_total: int = 0  # tiles that hold masked pixels (the others have no work and are done)
    tiles_done: int = 0
    pixels_total: int = 0  # pixels inside the mask
    pixels_done: int = 0  # ... in finished tiles
    pixels_running: int = 0  # ... solved so far in tiles still running (progress inside a tile)
    certified_pixels: int = 0  # ... that got a normal whose optimum was proved
    solved_pixels: int = 0  # ... that got a normal
    pixel_rate: float | None = None  # pixels per second in this run
    eps: float | None = None
    #: the raw values' step measured when the job started (storage.observations.raw_quantum):
    #: 16 for 12-bit data shifted into 16-bit files; None before the start
    raw_step: int | None = None
    owner_uid: str = ""  # the owner's token identity (storage.tokens): a re-created name is someone else
    label: str | None = None  # the client's name for the submission (maxfs submit resumes by it)
    name: str | None = None  # what people call the job: the dataset folder's name unless given
    uploaded_images: list[int] = field(default_factory=list)  # indices of the images stored, before start
    #: Why the calibration (lights, intensities, mask) looks wrong, from the input folder and from the
    #: checks after the solve (worker.calibration); empty when nothing is suspect.
    calibration: list[str] = field(default_factory=list)

    @property
    def solved_share(self) -> float | None:
        """Share of all masked pixels that got a normal: pixels of unfinished tiles (a cancelled
        or failed job) count as not solved, so a job stopped early never reads as complete."""
        return self.solved_pixels / self.pixels_total if self.pixels_done else None

    @property
    def certified_share(self) -> float | None:
        """Share of all masked pixels with a normal whose optimum was proved (never for ``l2``,
        which proves nothing); unfinished pixels count as not certified."""
        return self.certified_pixels / self.pixels_total if self.pixels_done else None

    @property
    def unfinished_pixels(self) -> int:
        """Masked pixels in tiles not computed (yet)."""
        return max(self.pixels_total - self.pixels_done, 0)

    @property
    def eta_seconds(self) -> float | None:
        """Seconds left at this run's pixel rate (active jobs only)."""
        if not (self.pixel_rate and self.state.active):
            return None
        return max(self.pixels_total - self.pixels_done - self.pixels_running, 0) / self.pixel_rate

    def warnings(self) -> list[str]:
        """What a user must hear about a result that is technically complete."""
        out = []
        # of the finished pixels: unfinished ones are not a sign of a bad result
        share = self.solved_pixels / self.pixels_done if self.pixels_done else None
        if share is not None and share < LOW_SOLVED_SHARE:
            out.append(
                f"only {share:.1%} of the {self.pixels_done} masked pixels got a normal: most pixels have "
                "fewer than 3 usable images (shadowed, saturated or rank-deficient lights); check the "
                "mask, the shadow threshold and eps"
            )
        if self.state is JobState.DONE and self.pixels_total == 0:
            out.append("the mask selects no pixel: nothing was solved")
        out.extend(f"calibration suspect: {c}" for c in self.calibration)
        return out

    def to_json(self) -> dict[str, Any]:
        d = asdict(self)
        d["state"] = self.state.value
        return d

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> JobRecord:
        d = dict(d)
        d["state"] = JobState(d["state"])
        return cls(**d)


def save_record(job_dir: Path, rec: JobRecord) -> None:
    """Write the record atomically next to the store."""
    rec.updated_at = time.time()
    job_dir = Path(job_dir)
    fd, tmp = tempfile.mkstemp(prefix=".maxfs-job-", dir=job_dir)
    try:
        with os.fdopen(fd, "w") as f:
            json.dump(rec.to_json(), f, indent=1)
        os.replace(tmp, job_dir / RECORD_NAME)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def load_record(job_dir: Path) -> JobRecord:
    path = Path(job_dir) / RECORD_NAME
    try:
        return JobRecord.from_json(json.loads(path.read_text()))
    except FileNotFoundError:
        raise StoreError(f"{job_dir} has no job record ({RECORD_NAME})") from None
    except (ValueError, TypeError, KeyError) as e:
        raise StoreError(f"job record {path} is corrupt: {e}") from None
