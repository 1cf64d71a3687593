"""Sharing the workers fairly between users: Dask priorities by each user's backlog.

Every tile task gets a Dask priority (higher runs first): minus its *rank* in its
user's backlog when it is submitted (tiles go in batches: a batch ranks as its last tile).
A user's first queued tile ranks 0, the next 1, and so on across all of that user's
jobs; ranks are freed as tiles finish. So when
one user has a thousand tiles queued and another submits sixteen, the newcomer's tiles
rank 0..15 and overtake the first user's remaining ones (ranks in the hundreds): the
small job finishes within a few tiles' time instead of after the large one, and two
users with large jobs alternate. Nothing is held back from the scheduler (adaptive
clusters still see the whole backlog); only the order changes. Running tiles are never
interrupted by priority; a tile lasts seconds (bounded work per tile, cancel points).
A job's preparation tasks (the store check and the eps estimate) rank just ahead of its
user's next tile (:meth:`FairShare.prep_priority`), so a new job starts by the same rule.
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

    @staticmethod
    def batch_priority(first: int, n: int) -> int:
        """The Dask priority of a batch of ``n`` tiles whose first has rank ``first``: minus the
        rank of its *last* tile. With the first's, a newcomer's one-tile job (rank 0) tied with
        the other users' whole first batches and, queued later, waited for all of them."""
        return -(first + n - 1)

    def prep_priority(self, user: str) -> int:
        """The Dask priority of a job's preparation tasks (store check, eps estimate): one above
        what ``user``'s next tile would get, so a job's start is not queued behind the tiles of
        users with longer backlogs (a tile of the same rank already queued included)."""
        return 1 - self.backlog.get(user, 0)

    def release(self, user: str, n: int = 1) -> None:
        """``n`` of ``user``'s tiles finished (or were dropped)."""
        left = self.backlog.get(user, 0) - n
        if left > 0:
            self.backlog[user] = left
        else:
            self.backlog.pop(user, None)
