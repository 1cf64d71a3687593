"""Wall-clock time per phase of a command (``maxfs run --timings``)."""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager

#: The row for time outside every named phase.
OTHER = "other"


class Timings:
    """Phases in the order they ran; a phase entered twice adds up."""

    def __init__(self) -> None:
        self.t0 = time.perf_counter()
        self.phases: dict[str, float] = {}

    @contextmanager
    def phase(self, name: str) -> Iterator[None]:
        t = time.perf_counter()
        try:
            yield
        finally:
            self.add(name, time.perf_counter() - t)

    def add(self, name: str, seconds: float) -> None:
        self.phases[name] = self.phases.get(name, 0.0) + seconds

    def table(self) -> str:
        """A plain text table: phase, seconds, share of the total since construction."""
        total = time.perf_counter() - self.t0
        w = max(len(n) for n in [*self.phases, "phase", OTHER]) + 2
        rows = [f"{'phase':<{w}}{'seconds':>9}{'share':>8}"]
        for name, s in self.phases.items():
            rows.append(f"{name:<{w}}{s:9.2f}{s / total:8.0%}")
        rest = total - sum(self.phases.values())  # records, progress counts: the rows add up to the total
        rows.append(f"{OTHER:<{w}}{rest:9.2f}{rest / total:8.0%}")
        rows.append(f"{'total':<{w}}{total:9.2f}{1:8.0%}")
        return "\n".join(rows)
