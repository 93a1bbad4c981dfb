"""`trapflow tap`: subscribe to a pipeline's taps, decode through messages.py, print.

Owns a SUB socket connected to the broker's tap and the normalizer's result tap.
PUB sockets drop for slow subscribers, so a tap never slows the pipeline.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

import zmq

from trapflow.config import schema as configmod
from trapflow.errors import ProtocolError, StartupError
from trapflow.wire import jpeg, tap_msgs
from trapflow.wire.endpoints import Endpoints
from trapflow.wire.transport import SocketSpec, new_context, open_socket

# Nothing for this long: say once that the tap is waiting (no pipeline may be running yet).
WAITING_NOTICE_S = 1.0

TOPICS = {
    "results": (tap_msgs.TOPIC_RESULT,),
    "frames": (tap_msgs.TOPIC_META,),
    "stats": (tap_msgs.TOPIC_STATS,),
    "truth": (tap_msgs.TOPIC_TRUTH,),
    "all": (tap_msgs.TOPIC_RESULT, tap_msgs.TOPIC_META, tap_msgs.TOPIC_STATS,
            tap_msgs.TOPIC_TRUTH),
}


def describe(msg: tap_msgs.TapMessage, frames: list[bytes]) -> str:
    """One printable line for a tap message."""
    if isinstance(msg, tap_msgs.TapResult):
        return "result " + msg.line.decode("utf-8", "replace")
    if isinstance(msg, (tap_msgs.TapMeta, tap_msgs.TapPair, tap_msgs.TapPreview)):
        p = msg.header
        lat_ms = (time.monotonic_ns() - p.t_mono_ns) / 1e6
        sizes = (f" {len(frames[2])}+{len(frames[3])} B"
                 if isinstance(msg, (tap_msgs.TapPair, tap_msgs.TapPreview)) else "")
        return (f"frame seq={p.seq} {p.width}x{p.height} {p.encoding}{sizes} "
                f"skew={p.skew_ns / 1e6:.2f}ms age={lat_ms:.1f}ms source={p.source}")
    if isinstance(msg, tap_msgs.TapStats):
        s = msg.stats
        pools = " ".join(f"{n}:{p.processed}/{p.dropped}d/{p.rate}Hz" for n, p in s.pools.items())
        return f"stats up={s.uptime_s:.0f}s in={s.pairs_in} ({s.rate_in}/s) {pools}"
    t = msg.truth
    objs = ", ".join(f"{o.label}@{[round(v) for v in o.box]}" for o in t.objects)
    return f"truth seq={t.seq} scene={t.scene_label} [{objs}]"


def run_tap(what: str, run_dir: Path, endpoints: list[str], count: int | None = None,
            save_frames: Path | None = None, timeout_s: float | None = None,
            cfg: configmod.Config | None = None,
            notice: Callable[[str], None] | None = None) -> int:
    """Print tap messages until count, timeout or Ctrl-C; return how many were printed.

    When nothing comes for WAITING_NOTICE_S, `notice` is told once that the tap is waiting
    (and where), so a tap started before its pipeline does not look hung."""
    topics = list(TOPICS[what])
    if save_frames is not None:
        save_frames.mkdir(parents=True, exist_ok=True)
        topics = [t for t in topics if t != tap_msgs.TOPIC_META] + [tap_msgs.TOPIC_IMAGE]
    if not endpoints:
        if not run_dir.exists():
            raise StartupError(f"no run directory {run_dir}: is a pipeline running there?")
        ep = Endpoints.for_run((cfg or configmod.Config()).network, run_dir)
        endpoints = [ep.tap, ep.results_tap]
    ctx = new_context()
    n = 0
    started = time.monotonic()
    deadline = started + timeout_s if timeout_s else None
    waiting_said = notice is None
    try:
        sub = open_socket(ctx, SocketSpec(zmq.SUB, endpoints[0], subscribe=tuple(topics),
                                          rcvhwm=100, also_connect=tuple(endpoints[1:])))
        while count is None or n < count:
            wait_ms = 200 if deadline is None else int(max(0.0, deadline - time.monotonic()) * 1000)
            if deadline is not None and wait_ms == 0:
                break
            if not sub.poll(min(wait_ms, 200), zmq.POLLIN):
                if not waiting_said and n == 0 and time.monotonic() - started >= WAITING_NOTICE_S:
                    assert notice is not None
                    notice(f"waiting for a pipeline: nothing yet from {', '.join(endpoints)}")
                    waiting_said = True
                continue
            frames = sub.recv_multipart()
            msg: tap_msgs.TapMessage | None = None
            try:
                msg = tap_msgs.decode_tap(frames)
                line = describe(msg, frames)
            except ProtocolError as exc:
                line = f"malformed tap message: {exc}"
            if save_frames is not None and isinstance(msg, tap_msgs.TapPair):
                # Photos on disk: a raw pair (the default ring) is encoded here, once, at
                # the quality a JPEG pipeline would have used.
                p, left, right = jpeg.to_jpeg_pair(msg.header, msg.left, msg.right,
                                                   configmod.DEFAULT_JPEG_QUALITY)
                (save_frames / f"{p.seq:08d}_left.jpg").write_bytes(left)
                (save_frames / f"{p.seq:08d}_right.jpg").write_bytes(right)
            print(line, flush=True)
            n += 1
    except KeyboardInterrupt:
        pass
    finally:
        ctx.destroy(linger=0)
    return n
