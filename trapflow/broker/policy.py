"""The only place that decides what to drop: per-pool pending buffers (the policy grammar,
Policy and parse_policy, lives with the config in trapflow.config.schema).

latest     keep only the newest pair (slow recognisers always see fresh frames)
fifo:N     bounded queue, oldest dropped when full
ordered:N  one stateful worker, in order, bounded; when full the NEWEST pair is dropped,
           so the worker sees long contiguous runs and one gap per overload, not a gap
           before every pair (visual odometry re-initialises on each gap)

Whatever the policy, a pool's max_pending_age_s drops pairs that waited longer (stale).
"""

from __future__ import annotations

from collections import deque

from trapflow.config.schema import Policy


class Pending:
    """Sequence numbers waiting for a worker of one pool, with the pool's drop rule and
    the time each arrived (for the pool's max_pending_age_s)."""

    def __init__(self, policy: Policy) -> None:
        self.policy = policy
        self._q: deque[int] = deque()
        self._born: dict[int, float] = {}

    def __len__(self) -> int:
        return len(self._q)

    def push(self, seq: int, now: float = 0.0) -> list[int]:
        """Queue seq (arrived at `now`); return the sequence numbers this policy drops to
        make room."""
        if self.policy.kind == "ordered" and len(self._q) >= self.policy.bound:
            return [seq]
        dropped: list[int] = []
        while len(self._q) >= self.policy.bound:
            dropped.append(self._take_left())
        self._q.append(seq)
        self._born[seq] = now
        return dropped

    def requeue(self, seqs: list[tuple[int, float]]) -> list[int]:
        """Put pairs taken earlier back at the front, in seq order, with their arrival
        times (a recycled worker's pairs it never started); return what the policy drops
        to keep its bound: the oldest for latest and fifo, the newest for ordered."""
        for seq, born in sorted(seqs, reverse=True):
            self._q.appendleft(seq)
            self._born[seq] = born
        dropped: list[int] = []
        while len(self._q) > self.policy.bound:
            seq = self._q.pop() if self.policy.kind == "ordered" else self._q.popleft()
            self._born.pop(seq, None)
            dropped.append(seq)
        return dropped

    def expire(self, older_than: float) -> list[int]:
        """Remove and return the pairs that arrived before `older_than` (stale)."""
        stale = [seq for seq in self._q if self._born.get(seq, 0.0) < older_than]
        if stale:
            gone = set(stale)
            self._q = deque(seq for seq in self._q if seq not in gone)
            for seq in stale:
                del self._born[seq]
        return stale

    def born(self, seq: int) -> float:
        """When a pending pair arrived (0.0 if it is not pending)."""
        return self._born.get(seq, 0.0)

    def pop(self) -> int | None:
        """The next seq to dispatch, or None."""
        return self._take_left() if self._q else None

    def clear(self) -> list[tuple[int, float]]:
        """Remove and return everything pending, with arrival times."""
        out = [(seq, self._born.get(seq, 0.0)) for seq in self._q]
        self._q.clear()
        self._born.clear()
        return out

    def _take_left(self) -> int:
        seq = self._q.popleft()
        self._born.pop(seq, None)
        return seq
