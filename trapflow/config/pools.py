"""Worker pools: one pool of worker processes per algorithm, and the default pools."""

from __future__ import annotations

from typing import Annotated, Any, Literal

import msgspec

from trapflow.config.base import Section as _Section
from trapflow.config.policy import Policy, parse_policy


class PoolConfig(_Section):
    """One pool of identical worker processes running one algorithm."""

    count: Annotated[int, msgspec.Meta(ge=0, le=64)] = 1
    """Worker processes on this host (0 switches the pool off, or with `remote: true` leaves it to
    other hosts)."""
    plugin: str = ""
    """Registry name or `module:Class` of the plugin; empty: the pool's own name."""
    policy: str = "latest"
    """Queueing policy: `latest` (only the newest pair waits), `fifo:N` or `ordered[:N]` (one
    worker, in order; a drop reaches it as a gap)."""
    nice: Annotated[int, msgspec.Meta(ge=0, le=19)] = 0
    """Niceness added to the pool's processes (0..19), so visual odometry keeps its rate."""
    affinity: list[Annotated[int, msgspec.Meta(ge=0)]] = []
    """CPU cores the pool's processes may run on; empty: all."""
    credit: Annotated[int, msgspec.Meta(ge=1, le=64)] = 1
    """Pairs a worker may hold at once (prefetch)."""
    timeout_s: Annotated[float, msgspec.Meta(gt=0, le=3600)] = 10.0
    """A pair taking a worker longer than this is lost, the worker evicted and its process
    killed."""
    max_rss_mb: Annotated[int, msgspec.Meta(ge=0, le=1 << 20)] = 0
    """A worker whose resident memory (MiB) is past this after a pair is recycled: it
    finishes the pair, says goodbye and is replaced at once (0: no limit)."""
    max_jobs: Annotated[int, msgspec.Meta(ge=0)] = 0
    """A worker is recycled after this many pairs (processed or failed; 0: no limit)."""
    max_pending_age_s: Annotated[float, msgspec.Meta(ge=0, le=86400)] = 0.0
    """Pairs waiting in the pool's queue longer than this are dropped as stale (0: kept)."""
    max_detections: Annotated[int, msgspec.Meta(ge=1, le=100000)] = 256
    """Most detections one result of the pool may bring: the broker keeps the most confident
    and cuts the rest where results enter the trusted side (a school of fish, a snow storm or
    a broken model cannot stall the normalizer), counted per pool (ledger `boxes_cut`)."""
    params: dict[str, Any] = {}
    """Passed to the plugin's `configure()` (docs/plugins.md lists the built-in plugins' params)."""
    remote: bool = False
    """Workers on other hosts may join (`trapflow worker`); the broker sends them the bytes."""
    gate: Literal["always", "motion"] = "always"
    """always: every pair; motion: only pairs the motion gate lets through (the `gate:`
    section: motion, pre-roll, keep-alive, hold); the rest are counted `gated`."""
    debug: bool = False
    """The pool's processes log at debug level."""
    save: bool = False
    """The plugin may save debug images into the run directory (debug/)."""
    time: bool = False
    """Log each pair's processing time."""

    def __post_init__(self) -> None:
        parse_policy(self.policy)  # raises ValueError, reported with the key path
        if self.gate == "motion" and self.ordered:
            raise ValueError(
                f"expected gate: always with policy {self.policy}, got gate: motion: an "
                "ordered pool (visual odometry) needs every pair in sequence, and each "
                "pair the gate withholds would reach it as a gap that resets it")

    @property
    def parsed_policy(self) -> Policy:
        """The policy as an object."""
        return parse_policy(self.policy)

    @property
    def ordered(self) -> bool:
        """The pool sees its pairs one by one in capture order (policy `ordered`): its plugin
        may keep state from pair to pair (visual odometry). The broker queues it in order
        live; `trapflow process` gives it time-ordered chunks of its own."""
        return self.parsed_policy.kind == "ordered"


def _default_pools() -> dict[str, PoolConfig]:
    return {
        # Visual odometry keeps its rate: the recognisers run at a lower CPU priority, and
        # only on pairs the motion gate lets through (an empty sea floor costs almost
        # nothing; a rig that VO sees moving turns the gate off). VO is never gated.
        "mono": PoolConfig(count=1, policy="latest", nice=5, gate="motion"),
        "stereo": PoolConfig(count=1, policy="latest", nice=10, gate="motion"),
        "vo": PoolConfig(count=1, policy="ordered:16"),
        "tags": PoolConfig(count=0, policy="latest", nice=5),
    }
