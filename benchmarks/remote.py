"""Remote-pool benchmark: trapflow's remote wire over tcp with CURVE against raw pyzmq over
tcp, in one run, both between two processes on this host (127.0.0.1).

trapflow: the broker's side is a ROUTER opened by transport.open_socket with the pipeline's
CURVE keys and ZAP (zmq.auth); the worker's a DEALER with its own keys, which decodes and
checks every job (decode_job, check_pair_frames) and answers Done + an encoded Result, as a
remote worker does. Raw: the same ROUTER/DEALER pattern and payload, no keys, no decoding.
Throughput is lossless with a window of pairs in flight; latency is the round trip from
sending a pair to its answer, at a fixed rate. Writes remote.json and remote.md into --out
and prints the table.

Usage: python -m benchmarks.remote [--quick] [--repeats 1] [--seconds 3] [--out bench-results]
"""

from __future__ import annotations

import multiprocessing as mp
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

import zmq

from benchmarks import harness as h
from trapflow.wire import messages
from trapflow.wire.curve import client_keys, server_keys, start_authenticator
from trapflow.wire.keys import generate
from trapflow.wire.transport import SocketSpec, new_context, open_socket

WINDOW = 4  # pairs in flight, as a worker with credit 4
LATENCY_RATE_HZ = 30.0
LATENCY_PAIRS = 90


def payload() -> tuple[bytes, bytes]:
    """A 1280x720 JPEG pair of a textured scene (what a remote pool gets)."""
    import cv2
    import numpy as np

    rng = np.random.default_rng(1)
    base = cv2.GaussianBlur(rng.integers(0, 255, (720, 1280, 3), dtype=np.uint8), (0, 0), 1.2)
    q = [cv2.IMWRITE_JPEG_QUALITY, 90]
    return (cv2.imencode(".jpg", base, q)[1].tobytes(),
            cv2.imencode(".jpg", np.roll(base, 40, axis=1), q)[1].tobytes())


def header(seq: int) -> bytes:
    now = time.monotonic_ns()
    return messages.encode(messages.StereoPair(
        seq=seq, t_wall_ns=time.time_ns(), t_mono_ns=now, t_left_ns=now, t_right_ns=now,
        skew_ns=0, encoding="jpeg", width=1280, height=720))


def worker(mode: str, endpoint: str, keys: str) -> None:
    ctx = new_context()
    if mode == "raw":
        sock = ctx.socket(zmq.DEALER)
        sock.setsockopt(zmq.LINGER, 0)
        sock.connect(endpoint)
        sock.send(b"ready")
        while True:
            frames = sock.recv_multipart(copy=False)
            if len(frames) == 1:
                break
            sock.send_multipart([b"done", frames[1]])  # the header back as its "result"
    else:
        curve = client_keys(Path(keys)) if mode == "curve" else None
        sock = open_socket(ctx, SocketSpec(zmq.DEALER, endpoint, identity=b"w@bench:0:1",
                                           curve=curve))
        sock.send(messages.encode(messages.Ready(worker="w", pool="far", credit=WINDOW)))
        while True:
            frames = sock.recv_multipart(copy=False)
            if len(frames) == 1:
                break
            messages.decode_job(frames[0])
            pair = messages.check_pair_frames(frames[1:])
            result = messages.Result(seq=pair.seq, t_wall_ns=pair.t_wall_ns,
                                     t_mono_ns=pair.t_mono_ns, pool="far", worker="w",
                                     proc_ns=0, body=messages.MonoIR())
            sock.send_multipart([messages.encode(messages.Done(worker="w", pool="far",
                                                               seq=pair.seq)),
                                 messages.encode(result)])
    ctx.destroy(linger=0)


def measure(mode: str, folder: Path, left: bytes, right: bytes,
            seconds: float) -> dict[str, Any]:
    ctx = new_context()
    auth = None
    curve = None
    if mode == "curve":
        curve = server_keys(folder / "server.key_secret")
        auth = start_authenticator(ctx, folder / "authorized")
    if mode == "raw":
        router = ctx.socket(zmq.ROUTER)
        router.setsockopt(zmq.LINGER, 0)
        router.bind("tcp://127.0.0.1:*")
    else:
        router = open_socket(ctx, SocketSpec(zmq.ROUTER, "tcp://127.0.0.1:*", bind=True,
                                             curve=curve))
    endpoint = router.getsockopt_string(zmq.LAST_ENDPOINT)
    proc = mp.get_context("spawn").Process(target=worker,
                                           args=(mode, endpoint, str(folder / "worker")))
    proc.start()
    ident, _ = router.recv_multipart()
    job = messages.encode(messages.Job(pool="far"))
    frames = [job] if mode != "raw" else [b"job"]

    def send(seq: int) -> None:
        router.send_multipart([ident, *frames, header(seq), left, right], copy=False)

    # Throughput: keep WINDOW pairs in flight for `seconds`.
    seq = 0
    for _ in range(WINDOW):
        send(seq)
        seq += 1
    done = 0
    t0 = time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        router.recv_multipart()
        done += 1
        send(seq)
        seq += 1
    elapsed = time.perf_counter() - t0
    for _ in range(WINDOW):
        router.recv_multipart()
    # Latency: one pair at a time at LATENCY_RATE_HZ, round trip.
    lat = []
    for _ in range(LATENCY_PAIRS):
        t = time.perf_counter()
        send(seq)
        seq += 1
        router.recv_multipart()
        lat.append((time.perf_counter() - t) * 1000)
        time.sleep(max(0.0, 1 / LATENCY_RATE_HZ - (time.perf_counter() - t)))
    router.send_multipart([ident, b"stop"])
    proc.join(10)
    if auth is not None:
        auth.stop()
    ctx.destroy(linger=0)
    lat.sort()
    return {"mode": mode, "pairs_per_s": round(done / elapsed, 1),
            "mb_per_s": round(done * (len(left) + len(right)) / elapsed / 1e6, 1),
            "rtt_ms_p50": round(statistics.median(lat), 3),
            "rtt_ms_p99": round(lat[int(len(lat) * 0.99) - 1], 3)}


MODES = ("raw", "plain", "curve")


def result(report: dict[str, Any]) -> h.Result:
    """Per path the median of the runs, [min-max] when there were several."""
    r = h.Result("remote", "Remote pools over tcp (127.0.0.1)", key="path", data=report, notes=[
        f"1280x720 JPEG pairs ({report['pair_bytes']} bytes), window {WINDOW}; raw: pyzmq "
        "ROUTER/DEALER, nothing decoded; plain: trapflow's remote wire without keys; curve: "
        f"with CURVE and ZAP. Median of {report['repeats']} runs a path (interleaved)."])
    for mode in MODES:
        runs = [x for x in report["rows"] if x["mode"] == mode]

        def fig(key: str, unit: str = "", digits: int = 1, runs: list[dict[str, Any]] = runs,
                ) -> h.Figure:
            return h.figure(h.summarise([x[key] for x in runs]), unit, digits=digits)

        r.add(mode, **{"pairs/s": fig("pairs_per_s"), "MB/s": fig("mb_per_s"),
                       "round trip p50": fig("rtt_ms_p50", "ms", 3),
                       "round trip p99": fig("rtt_ms_p99", "ms", 3)})
    return r


def main() -> None:
    ap = h.options(__doc__, repeats=1, quick_help="1 s throughput windows")
    ap.add_argument("--seconds", type=float, default=3.0, help="per throughput run")
    args = ap.parse_args()
    seconds = 1.0 if args.quick else args.seconds
    left, right = payload()
    with tempfile.TemporaryDirectory(prefix="tf-bench-remote-") as tmp:
        folder = Path(tmp)
        generate(folder, "server")
        generate(folder / "worker", "client")
        (folder / "worker" / "server.key").write_bytes((folder / "server.key").read_bytes())
        (folder / "authorized").mkdir()
        (folder / "authorized" / "worker.key").write_bytes(
            (folder / "worker" / "client.key").read_bytes())
        rows = [measure(mode, folder, left, right, seconds)
                for _ in range(args.repeats) for mode in MODES]
    report = {"pair_bytes": len(left) + len(right), "window": WINDOW, "repeats": args.repeats,
              "rows": rows}
    results = [result(report)]
    h.write(args.out, "remote", results)
    print(h.markdown(results))


if __name__ == "__main__":
    main()
