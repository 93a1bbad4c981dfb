"""What every node shares with its supervisor: the ROS 2 lifecycle states a node reports in
its heartbeats, and the exit statuses that mean "recycled on purpose"."""

from __future__ import annotations

import enum

# Exit statuses of a worker recycled on purpose: past its pool's max_rss_mb, or done with
# its max_jobs. It answered its last pair and said goodbye to the broker; it is replaced at
# once, without back-off and outside the restart budget (sysexits' EX_TEMPFAIL and next).
EXIT_RECYCLED_RSS = 75
EXIT_RECYCLED_JOBS = 76
RECYCLE_EXITS = {EXIT_RECYCLED_RSS: "rss", EXIT_RECYCLED_JOBS: "jobs"}



class Lifecycle(str, enum.Enum):
    """ROS 2 lifecycle states, as nodes report them in heartbeats (a str: the wire form)."""

    UNCONFIGURED = "unconfigured"
    INACTIVE = "inactive"
    ACTIVE = "active"
    FINALIZED = "finalized"

    def __str__(self) -> str:
        return self.value

    @classmethod
    def parse(cls, text: str) -> Lifecycle | None:
        """The state named on the wire, or None for a name no node sends."""
        try:
            return cls(text)
        except ValueError:
            return None
