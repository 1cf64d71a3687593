"""Which jobs each user has, kept in memory, so no request reads every job record.

Built once when the server starts (one pass over the records, which the resume of
running jobs needs anyway), then kept up to date by the manager: a job is added when
it is created, removed when it is deleted. ``open`` holds the jobs of a user that may
be unfinished; it is checked against their records (a handful) when a quota is counted,
and shrinks as they turn out finished, so it needs no hook in the code that finishes
jobs. Creating a job, listing one's jobs and counting one's open jobs cost the user's
own jobs, never everyone's.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

from maxfs.storage.records import JobRecord


@dataclass
class JobIndex:
    owner: dict[str, tuple[str, str]] = field(default_factory=dict)  # job id -> (name, uid)
    created: dict[str, float] = field(default_factory=dict)  # job id -> created_at
    by_user: dict[str, list[str]] = field(default_factory=dict)  # name -> job ids, oldest first
    open: dict[str, set[str]] = field(default_factory=dict)  # name -> jobs that may be unfinished

    def add(self, rec: JobRecord) -> None:
        self.owner[rec.id] = (rec.owner, rec.owner_uid)
        self.created[rec.id] = rec.created_at
        ids = self.by_user.setdefault(rec.owner, [])
        ids.append(rec.id)
        if len(ids) > 1 and self.created[ids[-2]] > rec.created_at:
            ids.sort(key=lambda j: self.created[j])
        if not rec.state.final:
            self.open.setdefault(rec.owner, set()).add(rec.id)

    def reopen(self, rec: JobRecord) -> None:
        """A finished job was started again."""
        self.open.setdefault(rec.owner, set()).add(rec.id)

    def remove(self, job_id: str) -> None:
        name, _ = self.owner.pop(job_id, ("", ""))
        self.created.pop(job_id, None)
        if job_id in self.by_user.get(name, []):
            self.by_user[name].remove(job_id)
            if not self.by_user[name]:
                del self.by_user[name]
        self.open.get(name, set()).discard(job_id)

    def jobs_of(self, name: str) -> list[str]:
        return list(self.by_user.get(name, []))

    def everyone(self) -> list[str]:
        return sorted(self.owner, key=lambda j: self.created[j])

    def count_open(self, name: str, record: Callable[[str], JobRecord | None]) -> int:
        """Unfinished jobs of ``name``, reading only the records of those that may be."""
        ids = self.open.get(name, set())
        for job_id in list(ids):
            rec = record(job_id)
            if rec is None or rec.state.final:
                ids.discard(job_id)
        return len(ids)
