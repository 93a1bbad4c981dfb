"""Benchmark of the live viewer: CPU of the viewer process over a window while a client
polls it as the page does, against the default pipeline (1280x720 JPEG at 15 Hz).

CPU share = CPU seconds (user + system) of the viewer node over the window / the window.
Usage: python scripts/bench_viewer.py [--seconds 30 --warmup 15 --out bench-results]
       [--baseline: also the broker's share in the same pipeline without a viewer]
"""

from __future__ import annotations

import argparse
import contextlib
import json
import signal
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import psutil

POLL_S = 0.5  # what the page does: /api/state twice a second, both images when they change


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


def _get(url: str) -> bytes:
    with urllib.request.urlopen(url, timeout=5) as r:
        body: bytes = r.read()
        return body


def _node(pipeline: subprocess.Popen[bytes], title: str) -> psutil.Process | None:
    for kid in psutil.Process(pipeline.pid).children(recursive=True):
        try:
            if kid.cmdline()[:1] == [title]:
                return kid
        except psutil.Error:
            continue
    return None


@contextlib.contextmanager
def _pipeline(titles: tuple[str, ...], *args: str) -> Iterator[list[psutil.Process]]:
    """A default pipeline started with `args` (stopped with SIGINT on leaving), once its
    nodes named by `titles` are up: those nodes' processes."""
    run = Path(tempfile.mkdtemp(prefix="tf-bench-")) / "run"
    pipeline = subprocess.Popen(
        [sys.executable, "-m", "trapflow", "start", "--run-dir", str(run), *args],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        deadline = time.monotonic() + 120
        while None in (nodes := [_node(pipeline, t) for t in titles]):
            if time.monotonic() > deadline or pipeline.poll() is not None:
                raise SystemExit(f"the pipeline did not start {', '.join(titles)} within 120 s")
            time.sleep(0.5)
        yield [n for n in nodes if n is not None]
    finally:
        pipeline.send_signal(signal.SIGINT)
        try:
            pipeline.wait(30)
        except subprocess.TimeoutExpired:
            pipeline.kill()


def baseline(seconds: float, warmup: float) -> float:
    """The broker's CPU share in the same pipeline without a viewer (no image tap)."""
    with _pipeline(("trapflow:broker",)) as (broker,):
        time.sleep(warmup)
        t0, b0 = time.monotonic(), broker.cpu_times()
        time.sleep(seconds)
        b1 = broker.cpu_times()
        share: float = ((b1.user + b1.system) - (b0.user + b0.system)) / (time.monotonic() - t0)
        return share


def bench(seconds: float, warmup: float) -> dict[str, Any]:
    port = _free_port()
    base = f"http://127.0.0.1:{port}"
    with _pipeline(("trapflow:viewer", "trapflow:broker"), "--view", str(port)) as nodes:
        viewer, broker = nodes
        time.sleep(warmup)
        in0 = json.loads(_get(f"{base}/api/state"))["pairs_in"]
        t0, c0, b0 = time.monotonic(), viewer.cpu_times(), broker.cpu_times()
        seq, polls, pairs = None, 0, 0
        while time.monotonic() - t0 < seconds:
            state = json.loads(_get(f"{base}/api/state"))
            polls += 1
            frame = state.get("frame")
            if frame and frame["seq"] != seq:
                seq = frame["seq"]
                for side in ("left", "right"):
                    _get(f"{base}/frame/{seq}/{side}.jpg")
                pairs += 1
            time.sleep(POLL_S)
        dt = time.monotonic() - t0
        c1, b1 = viewer.cpu_times(), broker.cpu_times()
        final = json.loads(_get(f"{base}/api/state"))
    cpu = (c1.user + c1.system) - (c0.user + c0.system)
    bcpu = (b1.user + b1.system) - (b0.user + b0.system)
    return {"window_s": round(dt, 1), "viewer_cpu_s": round(cpu, 3),
            "viewer_cpu_share": round(cpu / dt, 4), "broker_cpu_share": round(bcpu / dt, 4),
            "capture_rate_hz": round((final["pairs_in"] - in0) / dt, 2),
            "pairs_tapped": final["frames"]["received"],
            "pairs_shown": final["frames"]["shown"], "client_polls": polls,
            "client_pairs": pairs}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--seconds", type=float, default=30.0, help="measurement window")
    ap.add_argument("--warmup", type=float, default=15.0, help="seconds after start-up")
    ap.add_argument("--out", default="bench-results", help="folder for viewer.json, viewer.md")
    ap.add_argument("--baseline", action="store_true",
                    help="also measure the broker without a viewer (another run as long)")
    args = ap.parse_args()
    r = bench(args.seconds, args.warmup)
    if args.baseline:
        r["broker_cpu_share_without_viewer"] = round(baseline(args.seconds, args.warmup), 4)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "viewer.json").write_text(json.dumps(r, indent=1) + "\n")
    (out / "viewer.md").write_text(
        "## Live viewer\n\n"
        f"Default pipeline ({r['capture_rate_hz']} pairs/s reached the broker), a client "
        f"polling as the page does for {r['window_s']} s: the viewer used "
        f"{r['viewer_cpu_s']} CPU s, "
        f"{100 * r['viewer_cpu_share']:.2f} % of a core (budget 3 %); it took "
        f"{r['pairs_tapped']} pairs from the tap and showed {r['pairs_shown']}. "
        f"Broker: {100 * r['broker_cpu_share']:.1f} % of a core"
        + (f" ({100 * r['broker_cpu_share_without_viewer']:.1f} % without a viewer)"
           if "broker_cpu_share_without_viewer" in r else "") + ".\n")
    print(json.dumps(r))


if __name__ == "__main__":
    main()
