"""Acoustic modem simulator: two pseudo-terminals joined by a slow, late, lossy channel.

Bytes written to one end come out of the other after the packet's airtime at the set
bit rate plus the latency; whole packets (frames as the sender cut them, or runs of
loose bytes) are lost, damaged or followed by noise with the set probabilities.
"""

from __future__ import annotations

import collections
import contextlib
import logging
import os
import random
import select
import threading
import time
import tty
from pathlib import Path

from trapflow.modem.frame import split_packets

log = logging.getLogger(__name__)

STALE_S = 1.0  # a partial packet older than this goes out as it is
MAX_QUEUE_BYTES = 1 << 16  # the modem's buffer; beyond it packets are lost (counted)


class _Direction:
    def __init__(self, name: str, src: int, dst: int) -> None:
        self.name = name
        self.src = src
        self.dst = dst
        self.buf = bytearray()
        self.buf_since = 0.0
        self.pending: collections.deque[tuple[float, bytes]] = collections.deque()
        self.pending_bytes = 0
        self.free_at = 0.0
        self.counts = collections.Counter[str]()


class LinkSimulator:
    """Two pty ends (a: the box, b: the surface) joined through a simulated modem link."""

    def __init__(
        self,
        bit_rate: float = 300.0,
        latency_s: float = 0.5,
        loss: float = 0.0,
        corrupt: float = 0.0,
        noise: float = 0.0,
        seed: int = 0,
        links: tuple[str | Path | None, str | Path | None] = (None, None),
    ) -> None:
        self.bit_rate = bit_rate
        self.latency_s = latency_s
        self.loss = loss
        self.corrupt = corrupt
        self.noise = noise
        self.rng = random.Random(seed)
        self._fds: list[int] = []
        ma, sa = self._pty()
        mb, sb = self._pty()
        self.ends = (os.ttyname(sa), os.ttyname(sb))
        self.links = links
        for link, end in zip(links, self.ends, strict=True):
            if link is not None:
                tmp = Path(f"{link}.tmp{os.getpid()}")
                tmp.unlink(missing_ok=True)
                tmp.symlink_to(end)
                os.replace(tmp, link)
        self.dirs = (_Direction("a->b", ma, mb), _Direction("b->a", mb, ma))

    def _pty(self) -> tuple[int, int]:
        master, slave = os.openpty()
        # Raw at once: a cooked pty would echo and translate line endings before a client opens it.
        tty.setraw(slave)
        os.set_blocking(master, False)
        self._fds += [master, slave]  # the slave stays open so clients may close and reopen
        return master, slave

    @property
    def names(self) -> tuple[str, str]:
        """What clients open: the symlinks when given, else the pty devices."""
        pairs = zip(self.links, self.ends, strict=True)
        a, b = (str(link) if link is not None else end for link, end in pairs)
        return a, b

    def _schedule(self, d: _Direction, packet: bytes, now: float) -> None:
        d.counts["packets"] += 1
        airtime = len(packet) * 10 / self.bit_rate
        d.free_at = max(now, d.free_at) + airtime
        if self.rng.random() < self.loss:
            d.counts["lost"] += 1
            return
        if d.pending_bytes + len(packet) > MAX_QUEUE_BYTES:
            d.counts["overflow"] += 1
            return
        if self.corrupt and self.rng.random() < self.corrupt:
            data = bytearray(packet)
            data[self.rng.randrange(len(data))] ^= 1 << self.rng.randrange(8)
            packet = bytes(data)
            d.counts["corrupted"] += 1
        if self.noise and self.rng.random() < self.noise:
            packet += bytes(self.rng.randrange(256) for _ in range(self.rng.randint(1, 8)))
            d.counts["noise"] += 1
        d.pending.append((d.free_at + self.latency_s, packet))
        d.pending_bytes += len(packet)

    def _pump_in(self, d: _Direction, now: float) -> None:
        try:
            data = os.read(d.src, 4096)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            return  # EIO: nobody has this end open right now
        if not d.buf:
            d.buf_since = now
        d.buf += data
        d.counts["bytes_in"] += len(data)
        for packet in split_packets(d.buf):
            self._schedule(d, packet, now)
        if not d.buf:
            d.buf_since = now

    def _pump_out(self, d: _Direction, now: float) -> None:
        if d.buf and now - d.buf_since > STALE_S:
            self._schedule(d, bytes(d.buf), now)
            d.buf.clear()
        while d.pending and d.pending[0][0] <= now:
            _, packet = d.pending.popleft()
            d.pending_bytes -= len(packet)
            try:
                os.write(d.dst, packet)
                d.counts["bytes_out"] += len(packet)
            except (BlockingIOError, OSError):
                d.counts["overflow"] += 1

    def run(self, stop: threading.Event) -> None:
        """Carry bytes both ways until stop is set."""
        try:
            while not stop.is_set():
                now = time.monotonic()
                due = [d.pending[0][0] for d in self.dirs if d.pending]
                due += [d.buf_since + STALE_S for d in self.dirs if d.buf]
                timeout = 0.2 if not due else max(0.0, min(0.2, min(due) - now))
                readable, _, _ = select.select([d.src for d in self.dirs], [], [], timeout)
                now = time.monotonic()
                for d in self.dirs:
                    if d.src in readable:
                        self._pump_in(d, now)
                    self._pump_out(d, now)
        finally:
            self.close()

    def stats(self) -> dict[str, dict[str, int]]:
        """Per direction: packets, lost, corrupted, noise, overflow, bytes in and out."""
        return {d.name: dict(d.counts) for d in self.dirs}

    def close(self) -> None:
        """Close both ptys and remove the symlinks."""
        for fd in self._fds:
            with contextlib.suppress(OSError):
                os.close(fd)
        self._fds = []
        for link, end in zip(self.links, self.ends, strict=True):
            if link is not None and os.path.islink(link) and os.readlink(link) == end:
                os.unlink(link)
