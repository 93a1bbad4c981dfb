"""The only place that decides what to drop: per-pool pending buffers.

latest     keep only the newest pair (slow recognisers always see fresh frames)
fifo:N     bounded queue, oldest dropped when full
ordered:N  one stateful worker, in order, bounded; when full the NEWEST pair is dropped,
           so the worker sees long contiguous runs and one gap per overload, not a gap
           before every pair (visual odometry re-initialises on each gap)
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

DEFAULT_ORDERED_BOUND = 16


@dataclass(frozen=True)
class Policy:
    """A parsed policy string."""

    kind: str  # "latest" | "fifo" | "ordered"
    bound: int

    def __str__(self) -> str:
        return "latest" if self.kind == "latest" else f"{self.kind}:{self.bound}"


def parse_policy(text: str) -> Policy:
    """Parse `latest`, `fifo:N` or `ordered[:N]`; ValueError says what was expected."""
    expected = f"expected latest, fifo:N or ordered[:N] with N >= 1, got {text!r}"
    kind, sep, num = text.strip().partition(":")
    if kind == "latest" and not sep:
        return Policy("latest", 1)
    if kind == "ordered" and not sep:
        return Policy("ordered", DEFAULT_ORDERED_BOUND)
    if kind in ("fifo", "ordered") and sep:
        try:
            bound = int(num)
        except ValueError:
            raise ValueError(expected) from None
        if bound >= 1:
            return Policy(kind, bound)
    raise ValueError(expected)


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
