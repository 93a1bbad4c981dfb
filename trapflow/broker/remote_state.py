"""What the broker knows of worker processes on other hosts, pure: who joined which pool
from which host, which local supervisor (owner) may report its death, and its rate.

No sockets, no clocks. The broker's state machine (broker.state) decides dispatch and
eviction for remote workers as for local ones; this table only names them for status.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

from trapflow.wire.messages import RemoteWorker

# Evicted remote workers still shown in status (oldest forgotten first).
MAX_EVICTED_SHOWN = 32
# Remote workers the table holds, live or joined: one more hello is refused (counted,
# refused_remote_table_full). 300 hellos from one authorised key once kept 300 entries and
# grew the broker by 11.7 MB (issue 26 item 10); a Pi takes a few remote workers, not 100s.
MAX_REMOTE_WORKERS = 128


@dataclass
class _Remote:
    host: str
    pool: str
    owner: bytes
    heard: float  # when it last spoke (any message on the remote socket)
    processed: int = 0
    last_processed: int = 0
    reason: str = ""  # why it was evicted; empty while it is live


class RemoteWorkers:
    """The remote workers that said hello, live or evicted."""

    def __init__(self) -> None:
        self.known: dict[bytes, _Remote] = {}
        self.owners: dict[bytes, float] = {}  # supervisor identity -> last heard (HostAlive)
        self.forgotten = 0  # joined, then silent before the broker took it as a worker

    def full(self, ident: bytes) -> bool:
        """Whether a hello from ident would pass MAX_REMOTE_WORKERS (one known may rejoin)."""
        if ident in self.known:
            return False
        return sum(1 for r in self.known.values() if not r.reason) >= MAX_REMOTE_WORKERS

    def heard(self, ident: bytes, now: float) -> None:
        """Any message from a remote identity: it is not stale."""
        r = self.known.get(ident)
        if r is not None:
            r.heard = now

    def forget_stale(self, now: float, liveness_s: float, live: Mapping[bytes, str]) -> int:
        """Forget workers that said hello but are not the broker's (never ready, or already
        gone) and were silent for liveness_s; returns how many (also in `forgotten`)."""
        stale = [i for i, r in self.known.items()
                 if not r.reason and i not in live and now - r.heard > liveness_s]
        for ident in stale:
            del self.known[ident]
        if stale:
            self.forgotten += len(stale)
            self._forget_owners()
        return len(stale)

    def joined(self, ident: bytes, host: str, pool: str, owner: bytes, now: float) -> bool:
        """A Hello was accepted: this identity belongs to that pool, host and owner.

        A worker says hello again with every heartbeat (so a restarted broker learns it);
        the same hello again changes nothing and returns False.
        """
        r = self.known.get(ident)
        if r is not None and (r.host, r.pool, r.owner) == (host, pool, owner):
            return False
        self.known.pop(ident, None)
        self.known[ident] = _Remote(host, pool, owner, heard=now)
        self.owners.setdefault(owner, now)  # a new owner gets its liveness from now on
        self._forget_owners()
        return True

    def owner_seen(self, owner: bytes, now: float) -> None:
        """A supervisor's heartbeat; only one that started a known worker is remembered."""
        if owner in self.owners:
            self.owners[owner] = now

    def silent(self, now: float, liveness_s: float, live: Mapping[bytes, str]) -> list[bytes]:
        """Live remote workers whose supervisor was not heard for liveness_s: host gone."""
        return [i for i, r in self.known.items() if i in live
                and now - self.owners.get(r.owner, now) > liveness_s]

    def _forget_owners(self) -> None:
        used = {r.owner for r in self.known.values()}
        for owner in [o for o in self.owners if o not in used]:
            del self.owners[owner]

    def pool_of(self, ident: bytes) -> str | None:
        """The pool a remote identity joined, or None if it never said hello."""
        r = self.known.get(ident)
        return r.pool if r is not None else None

    def may_report(self, sender: bytes, target: bytes) -> bool:
        """Only a remote worker itself, or the supervisor that started it, tells of its end."""
        r = self.known.get(target)
        return r is not None and sender in (target, r.owner)

    def processed(self, ident: bytes) -> None:
        """One result of this worker was taken."""
        r = self.known.get(ident)
        if r is not None:
            r.processed += 1

    def evicted(self, ident: bytes, reason: str) -> None:
        """The broker forgot this worker; it stays visible with the reason, bounded."""
        r = self.known.get(ident)
        if r is None:
            return
        r.reason = reason or "evicted"
        gone = [i for i, x in self.known.items() if x.reason]
        for old in gone[:max(0, len(gone) - MAX_EVICTED_SHOWN)]:
            del self.known[old]
        self._forget_owners()

    def stats(self, dt: float, live: Mapping[bytes, str]) -> list[RemoteWorker]:
        """Every known remote worker with its state and rate over the last dt seconds."""
        out = []
        for ident, r in self.known.items():
            if ident in live:
                r.reason = ""  # an evicted worker that spoke again is live again
            rate = (r.processed - r.last_processed) / dt if dt > 0 else 0.0
            r.last_processed = r.processed
            out.append(RemoteWorker(
                worker=ident.decode("utf-8", "replace"), host=r.host, pool=r.pool,
                state="active" if ident in live else "evicted", processed=r.processed,
                rate=round(rate, 2), reason=r.reason))
        return out
