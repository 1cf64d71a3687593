"""Sharing the workers fairly between users: Dask priorities by each user's backlog.

Every tile task gets a Dask priority (higher runs first): minus its *rank* in its
user's backlog when it is submitted. A user's first queued tile ranks 0, the next 1,
and so on across all of that user's jobs; ranks are freed as tiles finish. So when
one user has a thousand tiles queued and another submits sixteen, the newcomer's tiles
rank 0..15 and overtake the first user's remaining ones (ranks in the hundreds): the
small job finishes within a few tiles' time instead of after the large one, and two
users with large jobs alternate. Nothing is held back from the scheduler (adaptive
clusters still see the whole backlog); only the order changes. Running tiles are never
interrupted by priority; a tile lasts seconds (bounded work per tile, cancel points).
"""

from __future__ import annotations

#: Tiles per submission batch: one ``client.map`` call, and one priority, per batch.
BATCH = 8


class FairShare:
    """Per-user backlog counts for one server (or one ``maxfs run``)."""

    def __init__(self) -> None:
        self.backlog: dict[str, int] = {}

    def take(self, user: str, n: int) -> int:
        """Reserve ``n`` ranks for ``user``; the first one's rank (the batch's priority is minus it)."""
        first = self.backlog.get(user, 0)
        self.backlog[user] = first + n
        return first

    def release(self, user: str, n: int = 1) -> None:
        """``n`` of ``user``'s tiles finished (or were dropped)."""
        left = self.backlog.get(user, 0) - n
        if left > 0:
            self.backlog[user] = left
        else:
            self.backlog.pop(user, None)
