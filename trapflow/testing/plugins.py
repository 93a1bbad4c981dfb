"""Plugins for tests and benchmarks: no-op, deliberately slow, deliberately crashing, flaky,
a flood of boxes, and a digest of the bytes each pair carries. Named in a pool by their
import path (`trapflow.testing.plugins:Noop`) or by the short names trapflow.registry keeps
for them (noop, slow, crash, flaky, flood, digest), which it resolves but does not list."""

from __future__ import annotations

import hashlib
import os
import signal
import time
from collections.abc import Mapping
from typing import Any

from trapflow.plugin import Context, Detection, Extra, MonoIR, Pair, Worker, WorkerError

# One read per memory page, as a real consumer would touch its input.
PAGE = 4096


class Noop(Worker):
    """Touches every page of the payload without decoding it: measures the transport.

    Reports the capture-to-worker latency (monotonic clocks are system-wide).
    """

    needs_images = False

    def process(self, pair: Pair) -> Extra:
        lat_ns = time.monotonic_ns() - pair.header.t_mono_ns
        touched = int(pair.left[::PAGE].sum()) + int(pair.right[::PAGE].sum())
        return Extra(name="noop", fields={"gap": pair.gap, "lat_ns": lat_ns, "sum": touched})


class Slow(Worker):
    """Takes `delay_s` per pair (default 1 s) and reports which pair and gap it saw."""

    needs_images = False

    def configure(self, params: Mapping[str, Any], ctx: Context) -> None:
        self.delay = float(params.get("delay_s", 1.0))

    def process(self, pair: Pair) -> Extra:
        time.sleep(self.delay)
        return Extra(name="slow", fields={"gap": pair.gap})


class Burn(Worker):
    """Burns `cpu_s` of CPU per pair (default 0.1 s), spinning, never sleeping: a saturating
    recogniser for the VO floor benchmark."""

    needs_images = False

    def configure(self, params: Mapping[str, Any], ctx: Context) -> None:
        self.cpu_s = float(params.get("cpu_s", 0.1))

    def process(self, pair: Pair) -> Extra:
        end = time.process_time() + self.cpu_s
        n = 0
        while time.process_time() < end:
            n += 1
        return Extra(name="burn", fields={"spins": n})


class Digest(Worker):
    """A digest of the decoded pixels of both images: shows two paths deliver the same pair."""

    def configure(self, params: Mapping[str, Any], ctx: Context) -> None:
        self.pool = ctx.pool

    def process(self, pair: Pair) -> Extra:
        h = hashlib.sha1(pair.left.tobytes())
        h.update(pair.right.tobytes())
        return Extra(name="digest", fields={"sha1": h.hexdigest()[:16], "pool": self.pool,
                                            "shape": list(pair.left.shape),
                                            "encoding": pair.header.encoding,
                                            "mean": round(float(pair.left.mean()), 3)})


class Flood(Worker):
    """A detector gone wild (a school of fish, a snow storm, a broken model): `boxes`
    detections on every pair (default 1,000), small boxes on a grid, confidences spread."""

    needs_images = False

    def configure(self, params: Mapping[str, Any], ctx: Context) -> None:
        n = int(params.get("boxes", 1000))
        side = max(1, int(n**0.5) + 1)
        self.dets = [Detection(label="crab", confidence=round(0.3 + 0.7 * (i % 97) / 96, 3),
                               box=(float(4 * (i % side)), float(4 * (i // side)),
                                    float(4 * (i % side) + 3), float(4 * (i // side) + 3)))
                     for i in range(n)]

    def process(self, pair: Pair) -> MonoIR:
        return MonoIR(detections=self.dets)


class Flaky(Worker):
    """Fails every `every`-th pair with a WorkerError (bad input, as a plugin reports it)."""

    needs_images = False

    def configure(self, params: Mapping[str, Any], ctx: Context) -> None:
        self.every = int(params.get("every", 3))
        self.n = 0

    def process(self, pair: Pair) -> Extra:
        self.n += 1
        if self.n % self.every == 0:
            raise WorkerError(f"pair {pair.header.seq} rejected on purpose")
        return Extra(name="flaky", fields={"n": self.n})


class Crash(Worker):
    """Exits the process hard after `after` pairs, fails configure when `fail` is set, or
    is killed by SIGKILL in configure when `kill` is set (a worker killed while the
    pipeline starts)."""

    needs_images = False

    def configure(self, params: Mapping[str, Any], ctx: Context) -> None:
        if params.get("fail"):
            raise RuntimeError(str(params["fail"]))
        if params.get("kill"):
            os.kill(os.getpid(), signal.SIGKILL)
        self.left = int(params.get("after", 5))

    def process(self, pair: Pair) -> Extra:
        self.left -= 1
        if self.left < 0:
            os._exit(3)
        return Extra(name="crash", fields={"left": self.left})
