"""The only place that decides what to drop: per-pool pending buffers (the policy grammar,
Policy and parse_policy, lives with the config in trapflow.config).

latest     keep only the newest pair (slow recognisers always see fresh frames)
fifo:N     bounded queue, oldest dropped when full
ordered:N  one stateful worker, in order, bounded; when full the NEWEST pair is dropped,
           so the worker sees long contiguous runs and one gap per overload, not a gap
           before every pair (visual odometry re-initialises on each gap)
"""

from __future__ import annotations

from collections import deque

from trapflow.config import DEFAULT_ORDERED_BOUND as DEFAULT_ORDERED_BOUND
from trapflow.config import Policy as Policy
from trapflow.config import parse_policy as parse_policy


class Pending:
    """Sequence numbers waiting for a worker of one pool, with the pool's drop rule."""

    def __init__(self, policy: Policy) -> None:
        self.policy = policy
        self._q: deque[int] = deque()

    def __len__(self) -> int:
        return len(self._q)

    def push(self, seq: int) -> list[int]:
        """Queue seq; return the sequence numbers this policy drops to make room."""
        if self.policy.kind == "ordered" and len(self._q) >= self.policy.bound:
            return [seq]
        dropped: list[int] = []
        while len(self._q) >= self.policy.bound:
            dropped.append(self._q.popleft())
        self._q.append(seq)
        return dropped

    def pop(self) -> int | None:
        """The next seq to dispatch, or None."""
        return self._q.popleft() if self._q else None

    def clear(self) -> list[int]:
        """Remove and return everything pending."""
        out = list(self._q)
        self._q.clear()
        return out
