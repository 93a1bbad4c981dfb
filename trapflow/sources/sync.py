"""Pair two independently clocked frame streams by timestamp within a tolerance.

Pure (no threads, no devices): live sources push frames in as they arrive and pop
matched pairs; unmatched frames are dropped and counted, and the skew of every pair
feeds the mean/max skew that the stats report.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import Generic, TypeVar

T = TypeVar("T")

#: frames kept per side while waiting for a partner; older ones are dropped
MAX_PENDING = 8


@dataclass
class SkewStats:
    """Pairing counters: pairs made, frames dropped per side, and the pair skew."""

    pairs: int = 0
    dropped_left: int = 0
    dropped_right: int = 0
    skew_sum_ns: int = 0
    skew_max_ns: int = 0

    @property
    def skew_mean_ns(self) -> float:
        """Mean absolute left-right skew over all pairs."""
        return self.skew_sum_ns / self.pairs if self.pairs else 0.0

    def add(self, skew_ns: int) -> None:
        """Count one pair with this skew."""
        s = abs(skew_ns)
        self.pairs += 1
        self.skew_sum_ns += s
        self.skew_max_ns = max(self.skew_max_ns, s)

    def as_dict(self) -> dict[str, float]:
        """Numbers for stats and status output."""
        return {
            "pairs": self.pairs,
            "dropped_left": self.dropped_left,
            "dropped_right": self.dropped_right,
            "skew_mean_ms": self.skew_mean_ns / 1e6,
            "skew_max_ms": self.skew_max_ns / 1e6,
        }


def default_tolerance_ns(rate_hz: float) -> int:
    """Half a frame period: the largest skew at which the nearest partner is unambiguous."""
    return int(0.5e9 / rate_hz)


class StereoSync(Generic[T]):
    """Matches left and right frames whose timestamps differ by at most tolerance_ns.

    Each stream must be pushed in non-decreasing time order (true of one camera).
    """

    def __init__(self, tolerance_ns: int, max_pending: int = MAX_PENDING) -> None:
        if tolerance_ns < 0:
            raise ValueError(f"tolerance must be >= 0 ns, got {tolerance_ns}")
        self.tolerance_ns = tolerance_ns
        self.max_pending = max_pending
        self.stats = SkewStats()
        self._left: deque[tuple[int, T]] = deque()
        self._right: deque[tuple[int, T]] = deque()

    def push_left(self, t_ns: int, item: T) -> None:
        """A left frame arrived."""
        self._left.append((t_ns, item))
        if len(self._left) > self.max_pending:
            self._left.popleft()
            self.stats.dropped_left += 1

    def push_right(self, t_ns: int, item: T) -> None:
        """A right frame arrived."""
        self._right.append((t_ns, item))
        if len(self._right) > self.max_pending:
            self._right.popleft()
            self.stats.dropped_right += 1

    def pop(self) -> tuple[int, T, int, T] | None:
        """The oldest matched pair (t_left, left, t_right, right), or None if none yet."""
        tol = self.tolerance_ns
        while self._left and self._right:
            tl, left = self._left[0]
            tr, right = self._right[0]
            if tl < tr - tol:  # no later right frame can be closer: left is orphaned
                self._left.popleft()
                self.stats.dropped_left += 1
                continue
            if tr < tl - tol:
                self._right.popleft()
                self.stats.dropped_right += 1
                continue
            # Within tolerance; a next frame already here may be an even closer partner.
            if len(self._right) > 1 and abs(self._right[1][0] - tl) < abs(tr - tl):
                self._right.popleft()
                self.stats.dropped_right += 1
                continue
            if len(self._left) > 1 and abs(self._left[1][0] - tr) < abs(tl - tr):
                self._left.popleft()
                self.stats.dropped_left += 1
                continue
            self._left.popleft()
            self._right.popleft()
            self.stats.add(tl - tr)
            return tl, left, tr, right
        return None

    def flush(self) -> None:
        """Drop whatever is still waiting (end of stream); counted as dropped."""
        self.stats.dropped_left += len(self._left)
        self.stats.dropped_right += len(self._right)
        self._left.clear()
        self._right.clear()
