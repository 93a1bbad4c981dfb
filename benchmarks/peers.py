"""Peers benchmark: trapflow's path beside raw pyzmq, dora-rs, Eclipse Zenoh and Cyclone DDS.

One run, one machine, the same pairs: 1 source -> 1 consumer, lossless with back-pressure
(4 pairs in flight), JPEG pairs (2 x 1280x720 q90) and raw pairs (2 x 1280x720x3 uint8).
Consumers check the order of what they get (lost, reordered) and touch every page; nothing
is decoded. Ratios are against raw pyzmq PUSH/PULL over ipc in the same run. A peer that
does not import or start is a row that says why, never dropped.

Each peer moves [seq, stamp | left | right] as one message and is held to the window by an
acknowledgement per pair on the peer's own transport (the consumer answers each pair's seq):
  zenoh      put/subscribe between two peer sessions over tcp on 127.0.0.1, reliable, with
             congestion control BLOCK; payloads above 3 KB go through Zenoh's shared-memory
             pool (transport optimisation; the Python binding reads and writes a shared
             buffer only as a copy of bytes, so this is its fastest shared-memory path)
  cyclonedds reliable, keep-last with depth 4, loopback only, a domain of its own; two
             rows: a sequence<octet> topic (the Python binding packs and unpacks it byte
             by byte) and an octet[N] topic of the pair's size (one block each way)
  dora       a dataflow of a source node and a consumer node, run by `dora run` (its daemon
             in isolation, no coordinator) in a temporary folder; the ack is a dora output
The bench's own processes are children of this one; each is stopped by its pid, and the
dora run by its process group (it starts one), at the end of its row.

Usage: python -m benchmarks.peers [--quick] [--seconds 3] [--only ROWS] [--out DIR]
Writes DIR/peers.json and DIR/peers.md; prints the table.
"""

from __future__ import annotations

import argparse
import contextlib
import gc
import json
import os
import queue
import shutil
import signal
import socket
import struct
import subprocess
import sys
import tempfile
import time
import types
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np
import zmq

from benchmarks import harness as h
from benchmarks import transport as bt  # its payload and its paths

PAGE = bt.PAGE
WINDOW = bt.WINDOW
PREFIX = struct.Struct("<qq")  # seq, source's monotonic stamp (ns); seq < 0: control
PING, END = -2, -1
PEERS = ("zenoh", "cyclonedds", "cyclonedds-array", "dora")
PACKAGES = {"zenoh": "eclipse-zenoh", "cyclonedds": "cyclonedds",
            "cyclonedds-array": "cyclonedds", "dora": "dora-rs"}
MODULES = {"zenoh": "zenoh", "cyclonedds": "cyclonedds", "cyclonedds-array": "cyclonedds",
           "dora": "dora"}
WARMUP_S = 0.5
# Loopback only, no multicast, and socket buffers that hold a window of fragments (with the
# defaults, a 600 kB sample's fragments overflow them and wait for NACK and repair).
CYCLONE_CONFIG = (
    "<CycloneDDS><Domain Id='any'><General><Interfaces><NetworkInterface name='lo'/>"
    "</Interfaces><AllowMulticast>false</AllowMulticast></General>"
    "<Discovery><ParticipantIndex>auto</ParticipantIndex><Peers><Peer address='127.0.0.1'/>"
    "</Peers></Discovery><Internal><SocketReceiveBufferSize min='4MB'/>"
    "<SocketSendBufferSize min='4MB'/></Internal></Domain></CycloneDDS>")
QUEUE = 64  # dora's input queues: the window bounds what waits; these only must not drop
START_TIMEOUT_S = 30.0


# --- what every peer's source and consumer do, whatever carries the bytes ------------------


def payloads(kind: str, n: int = 2 * WINDOW + 1) -> list[bytearray]:
    """n buffers of [prefix | left | right], written once; each send rewrites the prefix.
    More than the window: a transport that sends after its call returns (dora) never sees
    a buffer rewritten under it."""
    left, right = bt.make_payload(kind)
    return [bytearray(PREFIX.size) + left + right for _ in range(n)]


def _note(path: Path, text: str) -> None:
    """Write a file the parent polls for in one step: it never reads a half-written one."""
    tmp = path.with_name(path.name + ".part")
    tmp.write_text(text)
    os.replace(tmp, path)


class Consumer:
    """Counts pairs, checks their order and touches every page of each."""

    def __init__(self) -> None:
        self.n = self.reordered = 0
        self.last = -1
        self.odd: list[tuple[int, int]] = []  # (expected, got): the first few out of order

    def take(self, buf: Any) -> int:
        seq, _stamp = PREFIX.unpack_from(buf, 0)
        if seq >= 0:
            a = np.frombuffer(buf, np.uint8)
            int(a[::PAGE].sum())
            self.n += 1
            if seq != self.last + 1 and len(self.odd) < 8:
                self.odd.append((self.last + 1, int(seq)))
            if seq <= self.last:
                self.reordered += 1
            self.last = max(self.last, seq)
        return int(seq)

    def result(self) -> dict[str, Any]:
        return {"received": self.n, "reordered": self.reordered,
                "out_of_order": self.odd}


def run_source(send: Callable[[bytes | bytearray], None], acks: Callable[[float], list[int]],
               kind: str, seconds: float, out: Path) -> None:
    """Ping until the consumer answers, warm up, then send with WINDOW pairs in flight.

    Writes out/go (when the measured window starts) and out/source.json (what was sent)."""
    bufs = payloads(kind)
    deadline = time.monotonic() + START_TIMEOUT_S
    while True:  # a pair sent before the consumer is matched could be lost: ping first
        send(PREFIX.pack(PING, 0))
        if PING in acks(0.05):
            break
        if time.monotonic() > deadline:
            raise SystemExit(f"source: no answer from the consumer in {START_TIMEOUT_S:.0f} s")
    seq = acked = 0
    first = -1
    t0 = time.monotonic()
    while True:
        now = time.monotonic()
        if first < 0 and now - t0 >= WARMUP_S:
            first, t0 = seq, now
            _note(out / "go", str(seq))
        elif first >= 0 and now - t0 >= seconds:
            break
        if seq - acked >= WINDOW:
            got = [s for s in acks(1.0) if s >= 0]
            acked = max([acked, *[s + 1 for s in got]])
            continue
        buf = bufs[seq % len(bufs)]
        PREFIX.pack_into(buf, 0, seq, time.monotonic_ns())
        send(buf)
        seq += 1
    end = time.monotonic() + 10
    while acked < seq and time.monotonic() < end:
        got = [s for s in acks(0.2) if s >= 0]
        acked = max([acked, *[s + 1 for s in got]])
    dt = time.monotonic() - t0
    send(PREFIX.pack(END, 0))
    _note(out / "source.json", json.dumps(
        {"first": first, "sent": seq, "acked": acked, "window_s": dt}))


def run_consumer(recv: Callable[[float], Any], ack: Callable[[int], None], out: Path) -> None:
    """Take pairs until END; answer each with its seq. Writes out/consumer.json."""
    c = Consumer()
    deadline = time.monotonic() + START_TIMEOUT_S + 60
    while time.monotonic() < deadline:
        buf = recv(0.5)
        if buf is None:
            continue
        seq = c.take(buf)
        if seq == END:
            break
        ack(seq)
    _note(out / "consumer.json", json.dumps(c.result()))


# --- the peers' nodes (run as `python -m benchmarks.peers --node PEER-ROLE`) -----------------


def zenoh_node(role: str, kind: str, seconds: float, out: Path, port: int) -> None:
    import zenoh

    conf = zenoh.Config()
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("transport/shared_memory/enabled", "true")
    # Zenoh's default pool (16 MB) holds fewer than three raw pairs: room for the window.
    conf.insert_json5("transport/shared_memory/transport_optimization/pool_size",
                      str(64 * 1024 * 1024))
    where = "listen" if role == "consumer" else "connect"
    conf.insert_json5(f"{where}/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    session = zenoh.open(conf)
    mine, theirs = ("bench/pairs", "bench/acks") if role == "source" else ("bench/acks",
                                                                           "bench/pairs")
    pub = session.declare_publisher(mine, congestion_control=zenoh.CongestionControl.BLOCK,
                                    reliability=zenoh.Reliability.RELIABLE)
    inbox: queue.SimpleQueue[bytes] = queue.SimpleQueue()
    sub = session.declare_subscriber(theirs, lambda s: inbox.put(s.payload.to_bytes()))

    def recv(timeout: float) -> bytes | None:
        try:
            return inbox.get(timeout=timeout)
        except queue.Empty:
            return None

    try:
        if role == "source":
            def acks(timeout: float) -> list[int]:
                got = [] if (first := recv(timeout)) is None else [first]
                while not inbox.empty():
                    got.append(inbox.get())
                return [PREFIX.unpack(x)[0] for x in got]

            run_source(pub.put, acks, kind, seconds, out)
        else:
            _note(out / "ready", "")
            run_consumer(recv, lambda seq: pub.put(PREFIX.pack(seq, 0)), out)
    finally:
        sub.undeclare()
        session.close()


def cyclonedds_node(role: str, kind: str, seconds: float, out: Path, domain: int,
                    variant: str) -> None:
    from cyclonedds.core import (
        InstanceState,
        Policy,
        Qos,
        ReadCondition,
        SampleState,
        ViewState,
        WaitSet,
    )
    from cyclonedds.domain import DomainParticipant
    from cyclonedds.idl import IdlStruct
    from cyclonedds.idl.types import array, sequence, uint8
    from cyclonedds.pub import DataWriter
    from cyclonedds.sub import DataReader
    from cyclonedds.topic import Topic
    from cyclonedds.util import duration

    def idl(name: str, field: Any) -> Any:
        # Made here (cyclonedds is optional), the field's type given as an object: this
        # module's annotations are strings, which IdlStruct would look up in its globals.
        return dataclass(types.new_class(name, (IdlStruct,), {"typename": f"bench::{name}"},
                                         lambda ns: ns.update({"__annotations__":
                                                               {"data": field}})))

    size = len(payloads(kind, 1)[0])
    if variant == "sequence":  # IDL sequence<octet>: the binding packs it byte by byte
        pair_t, ack_t = idl("Pairs", sequence[uint8]), idl("Acks", sequence[uint8])
    else:  # IDL octet[N]: written and read as one block; every message is N bytes
        pair_t, ack_t = idl("Pairs", array[uint8, size]), idl("Acks", array[uint8, PREFIX.size])

    def fit(b: bytes | bytearray, n: int) -> bytes:
        return bytes(b) if variant == "sequence" else bytes(b).ljust(n, b"\0")

    dp = DomainParticipant(domain)
    qos = Qos(Policy.Reliability.Reliable(duration(seconds=10)), Policy.History.KeepLast(WINDOW))
    pairs = Topic(dp, "pairs", pair_t, qos=qos)
    answers = Topic(dp, "acks", ack_t, qos=qos)
    if role == "source":
        w, r = DataWriter(dp, pairs, qos=qos), DataReader(dp, answers, qos=qos)
    else:
        w, r = DataWriter(dp, answers, qos=qos), DataReader(dp, pairs, qos=qos)

    waitset = WaitSet(dp)
    waitset.attach(ReadCondition(r, SampleState.NotRead | ViewState.Any | InstanceState.Any))

    def take(timeout: float) -> list[bytes | bytearray]:
        samples = r.take(N=WINDOW * 4)
        if not samples and waitset.wait(duration(seconds=timeout)):
            samples = r.take(N=WINDOW * 4)
        # a sequence reads back as a list of ints
        return [s.data if isinstance(s.data, bytes | bytearray) else bytes(s.data)
                for s in samples]

    if role == "source":
        run_source(lambda b: w.write(pair_t(data=fit(b, size))),
                   lambda t: [PREFIX.unpack_from(x)[0] for x in take(t)], kind, seconds, out)
    else:
        pending: list[bytes | bytearray] = []

        def recv(timeout: float) -> bytes | bytearray | None:
            if not pending:
                pending.extend(take(timeout))
            return pending.pop(0) if pending else None

        _note(out / "ready", "")
        run_consumer(recv, lambda seq: w.write(ack_t(data=PREFIX.pack(seq, 0))), out)


def dora_node(role: str, kind: str, seconds: float, out: Path) -> None:
    import pyarrow as pa
    from dora import Node

    node = Node()
    if role == "source":
        def acks(timeout: float) -> list[int]:
            got: list[int] = []
            end = time.monotonic() + timeout
            while not got:
                left = end - time.monotonic()
                if left <= 0:
                    break
                event = node.next(timeout=left)
                if event is None:
                    break
                if event["type"] == "INPUT":
                    got.append(int(event["value"][0].as_py()))
            return got

        arrays: dict[int, Any] = {}  # an Arrow array over each of the source's buffers, made once

        def send(b: bytes | bytearray) -> None:
            if len(b) <= PREFIX.size:  # a ping or the end: small and short-lived
                node.send_output("pair", pa.array(np.frombuffer(b, np.uint8)))
                return
            a = arrays.get(id(b))
            if a is None:
                a = arrays[id(b)] = pa.Array.from_buffers(pa.uint8(), len(b),
                                                          [None, pa.py_buffer(b)])
            node.send_output("pair", a)

        run_source(send, acks, kind, seconds, out)
    else:
        held: list[Any] = []

        def recv(timeout: float) -> Any:
            held.clear()  # the previous pair's event, kept while its buffer was read
            event = node.next(timeout=timeout)
            if event is None or event["type"] != "INPUT":
                return None
            held.append(event)
            return event["value"].to_numpy(zero_copy_only=True)

        _note(out / "ready", "")
        run_consumer(recv, lambda seq: node.send_output("ack", pa.array([seq], pa.int64())), out)


# --- running one peer: processes, CPU, clean-up --------------------------------------------


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _cpu(procs: list[subprocess.Popen[bytes]]) -> float:
    """CPU seconds of these processes (siblings) and their descendants."""
    return sum(h.tree_cpu(p.pid) for p in procs)


def _me() -> list[str]:
    """The command that runs this module again (a peer's node)."""
    return [sys.executable, "-m", "benchmarks.peers"]


def _env(base: dict[str, str]) -> dict[str, str]:
    """The nodes run in their temporary folder: the repository is put on their path so
    that `-m benchmarks.peers` finds this module there."""
    repo = str(Path(__file__).resolve().parents[1])
    env = dict(base)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (repo, base.get("PYTHONPATH")) if p)
    return env


def _wait_for(path: Path, timeout: float, procs: list[subprocess.Popen[bytes]]) -> None:
    end = time.monotonic() + timeout
    while not path.exists():
        dead = [p for p in procs if p.poll() is not None]
        if dead:
            err = (dead[0].stderr.read() if dead[0].stderr else b"").decode(errors="replace")
            raise RuntimeError(f"exited with {dead[0].returncode} before {path.name}: "
                               f"{err.strip().splitlines()[-1:] or ['no output']}")
        if time.monotonic() > end:
            raise RuntimeError(f"no {path.name} after {timeout:.0f} s")
        time.sleep(0.01)


@contextlib.contextmanager
def _started(cmds: list[list[str]], cwd: Path,
             env: dict[str, str] | None = None) -> Iterator[list[subprocess.Popen[bytes]]]:
    """Start these commands, each in its own process group; stop them (by pid) at the end."""
    procs = [subprocess.Popen(c, cwd=cwd, env=env, stdout=subprocess.DEVNULL,
                              stderr=subprocess.PIPE, start_new_session=True) for c in cmds]
    try:
        yield procs
    finally:
        for p in procs:
            if p.poll() is None:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(p.pid, signal.SIGTERM)  # its own group: dora's nodes too
        for p in procs:
            try:
                p.wait(5)
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(p.pid, signal.SIGKILL)
                p.wait(5)


def _dora_yaml(d: Path, kind: str, seconds: float) -> Path:
    me = _me()

    def node(role: str) -> str:
        args = " ".join([*me[1:], "--node", f"dora-{role}", "--kind", kind, "--seconds",
                         str(seconds), "--dir", str(d)])
        return f"    path: {me[0]}\n    args: {args}\n"

    y = d / "dataflow.yml"
    y.write_text("nodes:\n"
                 "  - id: source\n" + node("source")
                 + f"    inputs:\n      ack:\n        source: consumer/ack\n"
                 f"        queue_size: {QUEUE}\n    outputs:\n      - pair\n"
                 "  - id: consumer\n" + node("consumer")
                 + f"    inputs:\n      pair:\n        source: source/pair\n"
                 f"        queue_size: {QUEUE}\n    outputs:\n      - ack\n")
    return y


def run_peer(peer: str, kind: str, seconds: float, tmp: Path) -> dict[str, Any]:
    """One peer moving `kind` pairs for `seconds`: pairs/s, CPU us/pair, lost, reordered."""
    try:
        version = metadata.version(PACKAGES[peer])
        __import__(MODULES[peer])
    except Exception as exc:  # noqa: BLE001 - not installed, or does not import here
        return {"error": f"does not import: {type(exc).__name__}: {exc} "
                         "(pip install -e .[peers])"}
    d = Path(tempfile.mkdtemp(prefix=f"{peer}-{kind}-", dir=tmp))
    me = _me()
    common = ["--kind", kind, "--seconds", str(seconds), "--dir", str(d)]
    env = _env(dict(os.environ))
    if peer == "dora":
        dora = Path(sys.executable).parent / "dora"
        cmds = [[str(dora) if dora.exists() else "dora", "run", "--log-level", "error",
                 str(_dora_yaml(d, kind, seconds))]]
    elif peer == "zenoh":
        port = str(_free_port())
        cmds = [me + ["--node", "zenoh-consumer", "--port", port] + common,
                me + ["--node", "zenoh-source", "--port", port] + common]
    else:
        domain = str(100 + os.getpid() % 100)  # a domain of its own on a shared machine
        env["CYCLONEDDS_URI"] = CYCLONE_CONFIG
        cmds = [me + ["--node", f"{peer}-consumer", "--domain", domain] + common,
                me + ["--node", f"{peer}-source", "--domain", domain] + common]
    try:
        with _started(cmds, d, env) as procs:
            _wait_for(d / "go", START_TIMEOUT_S + 10, procs)
            c0 = _cpu(procs)
            _wait_for(d / "source.json", seconds + 20, procs)
            cpu = _cpu(procs) - c0
            _wait_for(d / "consumer.json", 10, procs)
    except RuntimeError as exc:
        return {"version": version, "error": f"did not run: {exc}"}
    src = json.loads((d / "source.json").read_text())
    con = json.loads((d / "consumer.json").read_text())
    n = src["sent"] - src["first"]
    return {"version": version, "pairs": n, "pairs_s": n / src["window_s"],
            "cpu_us_per_pair": cpu / max(n, 1) * 1e6,
            # never received (a pair that came late is reordered, not lost)
            "lost": src["sent"] - con["received"],
            "reordered": con["reordered"], "out_of_order": con["out_of_order"]}


def run_baseline(kind: str, seconds: float, tmp: Path) -> dict[str, Any]:
    r = bt.raw_pyzmq(kind, seconds, None, tmp)
    return {"version": zmq.__version__, "pairs": r["pairs"], "pairs_s": r["pairs_s"],
            "cpu_us_per_pair": r["cpu_us_per_pair"], "lost": 0, "reordered": 0}


def run_trapflow(kind: str, seconds: float, tmp: Path, frames: str) -> dict[str, Any]:
    r = bt.trapflow_path(kind, seconds, None, 1, tmp, frames=frames)
    return {"version": metadata.version("trapflow"), "pairs": r["pairs"], "pairs_s": r["pairs_s"],
            "cpu_us_per_pair": r["cpu_us_per_pair"],
            "cpu_us_per_pair_by_process": r["cpu_us_per_pair_by_process"],
            "lost": r["lost"], "reordered": 0}


# --- report --------------------------------------------------------------------------------

ROWS = ("pyzmq", "trapflow-shm", "trapflow-zmq", *PEERS)
LABELS = {"pyzmq": "raw pyzmq PUSH/PULL ipc", "trapflow-shm": "trapflow (ring, default)",
          "trapflow-zmq": "trapflow (bytes through the broker)", "zenoh": "Eclipse Zenoh",
          "cyclonedds": "Eclipse Cyclone DDS, sequence<octet>",
          "cyclonedds-array": "Eclipse Cyclone DDS, octet[N]", "dora": "dora-rs"}


def result(out: dict[str, Any]) -> h.Result:
    m = out["machine"]
    r = h.Result("peers", f"Peers: 1 source -> 1 consumer, lossless, {WINDOW} pairs in flight "
                 "(same run, same pairs)", key="path", data=out, notes=[
        f"{m['date']}; {m['cores']} cores, load average {m['load_before']} before and "
        f"{m['load_after']} after the run; Python {m['python']}; windows of "
        f"{out['seconds']:g} s after {WARMUP_S} s warm-up. JPEG pair: 2 x 1280x720 q90 "
        f"({out['bytes']['jpeg']:,} B); raw pair: 2 x 1280x720x3 ({out['bytes']['raw']:,} "
        "B). x pyzmq: ratio to raw pyzmq in this run. CPU: every process of the path "
        "(source, consumer, broker, daemons). lost / reordered: JPEG+raw."])
    for row in ROWS:
        figures, errors = _row(out, row)
        r.add(LABELS[row], **figures)
        for e in errors:
            r.add("", version=h.Figure(f"({e})"))
    return r


def _row(out: dict[str, Any], row: str) -> tuple[dict[str, h.Figure], list[str]]:
    """One path's figures over both payloads, and the errors of the payloads it missed."""
    figures: dict[str, h.Figure] = {"version": h.Figure("")}
    errors, lost, reordered = [], [], []
    for kind, name in (("jpeg", "JPEG"), ("raw", "raw")):
        r = out[kind].get(row, {"error": "not run"})
        if "version" in r:
            figures["version"] = h.Figure(str(r["version"]))
        if "error" in r:
            errors.append(f"{kind}: {r['error']}")
            figures.update({f"{name} pairs/s": h.Figure(None), f"{name} x pyzmq": h.Figure(None),
                            f"{name} CPU": h.Figure(None, "us/pair")})
            continue
        base = out[kind]["pyzmq"].get("pairs_s")
        figures[f"{name} pairs/s"] = h.Figure(round(r["pairs_s"], 1), digits=0)
        figures[f"{name} x pyzmq"] = h.Figure(round(r["pairs_s"] / base, 3) if base else None)
        figures[f"{name} CPU"] = h.Figure(round(r["cpu_us_per_pair"]), "us/pair")
        lost.append(str(r["lost"]))
        reordered.append(str(r["reordered"]))
    figures["lost / reordered"] = h.Figure(
        f"{'+'.join(lost)} / {'+'.join(reordered)}" if lost else "-")
    return figures, errors


def main() -> None:
    ap = h.options(__doc__, repeats=1, quick_help="1 s windows")
    ap.add_argument("--seconds", type=float, default=3.0, help="measured window per path")
    ap.add_argument("--only", default=",".join(ROWS), help="rows to run, comma-separated")
    ap.add_argument("--node", help=argparse.SUPPRESS)  # internal: one peer's source/consumer
    ap.add_argument("--kind", default="jpeg", help=argparse.SUPPRESS)
    ap.add_argument("--dir", type=Path, help=argparse.SUPPRESS)
    ap.add_argument("--port", type=int, default=0, help=argparse.SUPPRESS)
    ap.add_argument("--domain", type=int, default=0, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.quick:
        args.seconds = 1.0
    if args.node:
        peer, role = args.node.rsplit("-", 1)
        if peer == "zenoh":
            zenoh_node(role, args.kind, args.seconds, args.dir, args.port)
        elif peer.startswith("cyclonedds"):
            cyclonedds_node(role, args.kind, args.seconds, args.dir, args.domain,
                            "array" if peer.endswith("-array") else "sequence")
        else:
            dora_node(role, args.kind, args.seconds, args.dir)
        return
    rows = [r for r in args.only.split(",") if r]
    unknown = set(rows) - set(ROWS)
    if unknown:
        ap.error(f"--only: expected some of {','.join(ROWS)}, got {','.join(sorted(unknown))}")
    gc.freeze()
    tmp = Path(tempfile.mkdtemp(prefix="tfpeers-"))
    out: dict[str, Any] = {
        "machine": {"cores": os.cpu_count(), "python": sys.version.split()[0],
                    "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
                    "load_before": " ".join(f"{x:.1f}" for x in os.getloadavg())},
        "seconds": args.seconds, "window": WINDOW,
        "bytes": {k: len(payloads(k, 1)[0]) - PREFIX.size for k in ("jpeg", "raw")}}
    for kind in ("jpeg", "raw"):
        out[kind] = {}
        for row in ROWS:
            if row not in rows and row != "pyzmq":
                out[kind][row] = {"error": "not run (--only)"}
                continue
            h.log("peers", f"{kind}: {row}")
            try:
                if row == "pyzmq":
                    out[kind][row] = run_baseline(kind, args.seconds, tmp)
                elif row.startswith("trapflow-"):
                    out[kind][row] = run_trapflow(kind, args.seconds, tmp, row.split("-")[1])
                else:
                    out[kind][row] = run_peer(row, kind, args.seconds, tmp)
            except Exception as exc:  # noqa: BLE001 - a failed row says why; table goes on
                out[kind][row] = {"error": f"{type(exc).__name__}: {exc}"}
    shutil.rmtree(tmp, ignore_errors=True)
    out["machine"]["load_after"] = " ".join(f"{x:.1f}" for x in os.getloadavg())
    tables = [result(out)]
    h.write(args.out, "peers", tables)
    print(h.markdown(tables))


if __name__ == "__main__":
    main()
