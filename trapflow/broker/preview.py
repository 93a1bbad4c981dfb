"""When the broker publishes the viewer's preview, pure: no sockets, `now` passed in.

A preview (trapflow.wire.tap_msgs.TOPIC_PREVIEW) is one pair made small, at the viewer's
frame rate, and only while a viewer subscribes to it (the viewer does while a page is
open): with no page open nothing is copied out of the ring or encoded. The pair chosen is
one given to a pool whose results the page draws on the left image (the mono detector,
the tag finder), so that its boxes arrive for the very pair shown; where no such pool took
a pair for a whole extra interval (none configured, switched off, gated on a still scene),
the next pair to arrive is taken instead, so the page never freezes.
"""

from __future__ import annotations

from collections.abc import Collection, Mapping
from typing import Protocol

# Plugins whose results the page draws on the left image (boxes, tag outlines).
DRAWN_PLUGINS = ("mono", "tags")


class _Pool(Protocol):
    @property
    def plugin(self) -> str: ...


def drawn_pools(pools: Mapping[str, _Pool]) -> frozenset[str]:
    """The pools whose results the page draws: by plugin, the pool's name where it names
    none (a pool's plugin defaults to its name)."""
    return frozenset(name for name, p in pools.items() if (p.plugin or name) in DRAWN_PLUGINS)


class PreviewClock:
    """Says, per pair arriving or dispatched, whether it is the next preview."""

    def __init__(self, interval_s: float, drawn: Collection[str]) -> None:
        if not interval_s > 0:
            raise ValueError(f"preview interval: expected more than 0 s, got {interval_s}")
        self.interval_s = interval_s
        self.drawn = frozenset(drawn)
        self.wanted = False
        self._due = 0.0  # the next preview may go from this time on
        self.published = 0

    def want(self, wanted: bool, now: float) -> None:
        """A viewer subscribed (a page opened) or the last one left: the first preview goes
        with the next pair, not an interval later."""
        if wanted and not self.wanted:
            self._due = now
        self.wanted = wanted

    def on_dispatch(self, pool: str, now: float) -> bool:
        """A pair was given to `pool`: True if it is the preview to publish now."""
        return self._take(now >= self._due and pool in self.drawn, now)

    def on_arrival(self, now: float) -> bool:
        """A pair arrived: True if it is the preview, because no drawn pool took one for an
        interval past the time one was due (at once where no pool is drawn)."""
        late = self._due + (self.interval_s if self.drawn else 0.0)
        return self._take(now >= late, now)

    def _take(self, take: bool, now: float) -> bool:
        if not (take and self.wanted):
            return False
        self._due = now + self.interval_s
        self.published += 1
        return True
