"""A bounded reorder window over rows keyed by frame number, pure: rows come in file order,
frames go out in increasing order with all their rows, holding at most `frames` frames.

A detections file is written frame by frame, so its frame numbers only grow; a detector
whose parallel workers finish a little out of order writes a frame's rows a few frames
late. Both come out exactly as a sort by frame would give them (a frame's rows in file
order). A row of a frame that has already gone out cannot be placed: `FrameOrderError`
says so, and the caller names the line.
"""

from __future__ import annotations

import heapq
from typing import Generic, TypeVar

T = TypeVar("T")

DEFAULT_FRAMES = 64  # frames with rows held back for rows that come late


class FrameOrderError(ValueError):
    """A row of a frame that has already gone out (more than the window late)."""


class FrameWindow(Generic[T]):
    """Holds the rows of the latest `frames` frame numbers seen; add() returns the frames
    that leave the window, lowest first, as (frame, rows)."""

    def __init__(self, frames: int = DEFAULT_FRAMES) -> None:
        if frames < 1:
            raise ValueError(f"frames: expected 1 or more, got {frames}")
        self.frames = frames
        self._rows: dict[int, list[T]] = {}
        self._order: list[int] = []  # heap of the frame numbers held
        self.last_out: int | None = None  # the last frame given out

    def add(self, frame: int, row: T) -> list[tuple[int, list[T]]]:
        """Hold one row; the frames pushed out of the window by it, lowest first."""
        if self.last_out is not None and frame <= self.last_out:
            raise FrameOrderError(
                f"frame {frame} comes after frame {self.last_out} was tracked: expected rows "
                f"sorted by frame (a row may come at most {self.frames} frames late); sort "
                "the file by its first column first (a stable sort keeps each frame's rows "
                "in order)")
        held = self._rows.get(frame)
        if held is None:
            self._rows[frame] = [row]
            heapq.heappush(self._order, frame)
        else:
            held.append(row)
        out = []
        while len(self._order) > self.frames:
            out.append(self._pop())
        return out

    def drain(self) -> list[tuple[int, list[T]]]:
        """Every frame still held, lowest first (at the end of the file)."""
        return [self._pop() for _ in range(len(self._order))]

    def _pop(self) -> tuple[int, list[T]]:
        frame = heapq.heappop(self._order)
        self.last_out = frame
        return frame, self._rows.pop(frame)
