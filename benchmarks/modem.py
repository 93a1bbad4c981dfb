"""Modem link bench: bytes per result (JSON vs link encoding), results per hour, outbox append rate.

Usage: python -m benchmarks.modem [--quick] [--repeats 3] [--out bench-results]
       [--bit-rate 300] [--bytes-per-hour 0] [--appends 2000]
Writes modem.json and modem.md into the output folder and prints the tables.
"""

from __future__ import annotations

import math
import tempfile
import time
from pathlib import Path
from typing import Any

import msgspec

from benchmarks import harness as h
from trapflow.config.modem import BITS_PER_BYTE, ModemConfig, OutboxConfig
from trapflow.modem.codec import LinkCodec
from trapflow.modem.frame import OVERHEAD, message_cost
from trapflow.modem.outbox import Outbox

TS = "2025-07-07 12:52:43.120"
C, S = round(math.cos(0.05), 4), round(math.sin(0.05), 4)
SAMPLES: dict[str, dict[str, Any]] = {
    "mono_ir": {"mono_ir": {"timestamp": TS, "seq": 1234, "label": "crab", "confidence": 0.71,
                            "box": [512.4, 300.8, 640.6, 410.1]}},
    "stereo_ir": {"stereo_ir": {"timestamp": TS, "seq": 1234, "label": "scallop",
                                "confidence": 0.93}},
    "stereo_vo": {"stereo_vo": {"timestamp": TS, "seq": 1234, "ok": True,
                                "Rt": [[C, -S, 0.0, 0.0123], [S, C, 0.0, -0.0051],
                                       [0.0, 0.0, 1.0, 0.1032]], "inliers": 120}},
    "tags": {"tags": {"timestamp": TS, "seq": 1234, "id": 3,
                      "corners": [[100.5, 200.1], [150.2, 200.3], [150.0, 250.7], [100.1, 250.2]],
                      "rotation": [C, -S, 0.0, S, C, 0.0, 0.0, 0.0, 1.0],
                      "translation": [0.1, 0.2, 1.5], "error": 0.4}},
    "health": {"health": {"timestamp": TS, "uptime_s": 86400, "cpu_pct": 55.5, "load1": 1.25,
                          "temp_c": 61.2, "mem_pct": 40.1, "disk_free_mb": 20000, "backlog": 12,
                          "link": "active", "pools": {"mono": [4.5, 10], "stereo": [1.0, 200],
                                                      "vo": [12.0, 0]}}},
}  # fmt: skip


def on_air(body_len: int, cfg: ModemConfig) -> float:
    """Link bytes per result when frames are packed full of results of this size."""
    floor = 1_000_000
    cost = message_cost(floor, floor + 50, b"x" * body_len)
    per_frame = max(1, (cfg.max_frame_payload - 3) // cost)
    return (OVERHEAD + 3 + per_frame * cost) / per_frame


def append_rate(n: int, fsync_interval_s: float) -> dict[str, float]:
    with tempfile.TemporaryDirectory() as tmp:
        box = Outbox(Path(tmp) / "o.sqlite", OutboxConfig(fsync_interval_s=fsync_interval_s))
        rec = SAMPLES["mono_ir"]
        start = time.perf_counter()
        for _ in range(n):
            box.append(rec)
        box.sync()
        elapsed = time.perf_counter() - start
        syncs = box.syncs
        box.close()
    return {"appends_per_s": round(n / elapsed, 1), "fsyncs": syncs, "n": n}


def per_kind(cfg: ModemConfig, budget: float) -> h.Result:
    """Bytes per result as JSON and in the link encoding, and results per hour."""
    codec = LinkCodec(cfg.labels)
    r = h.Result("modem", f"Modem link: {cfg.bit_rate:g} bit/s, budget {budget:.0f} B/h, "
                 f"frames up to {cfg.max_frame_payload} B payload", key="kind",
                 notes=["on air: link bytes per result with frames packed full of results "
                        "of this kind; results/h within the budget."],
                 data={"bit_rate": cfg.bit_rate, "budget_bytes_per_hour": budget,
                       "max_frame_payload": cfg.max_frame_payload})
    for kind, rec in SAMPLES.items():
        js = len(msgspec.json.encode(rec)) + 1  # one JSON line
        link = len(codec.encode(rec))
        air = on_air(link, cfg)
        r.add(kind, json=h.Figure(js, "B"), link=h.Figure(link, "B"),
              ratio=h.Figure(round(js / link, 2)), **{
                  "on air": h.Figure(round(air, 1), "B", digits=1),
                  "results/h": h.Figure(int(budget / air)),
                  "JSON results/h": h.Figure(int(budget / js))})
    return r


def appends(n: int, repeats: int) -> h.Result:
    """The outbox's append rate, fsync once a second and after every append."""
    r = h.Result("modem", "Outbox appends", key="fsync",
                 notes=[f"Median of {repeats} runs [min-max]."])
    for name, n_runs, interval in (("interval 1 s", n, 1.0),
                                   ("every append", max(50, n // 10), 1e-9)):
        runs = [append_rate(n_runs, interval) for _ in range(repeats)]
        r.add(name, appends=h.figure(h.summarise([x["appends_per_s"] for x in runs]), "/s",
                                     digits=0),
              fsyncs=h.Figure(int(runs[0]["fsyncs"])), n=h.Figure(n_runs))
    return r


def main() -> None:
    ap = h.options(__doc__, repeats=3, quick_help="a tenth of the appends")
    ap.add_argument("--bit-rate", type=float, default=300.0)
    ap.add_argument("--bytes-per-hour", type=int, default=0, help="0: the link's capacity")
    ap.add_argument("--appends", type=int, default=2000)
    args = ap.parse_args()
    cfg = ModemConfig(bit_rate=args.bit_rate, bytes_per_hour=args.bytes_per_hour)
    capacity = cfg.bit_rate / BITS_PER_BYTE * 3600
    budget = min(capacity, cfg.bytes_per_hour) if cfg.bytes_per_hour else capacity
    n = max(100, args.appends // 10) if args.quick else args.appends
    results = [per_kind(cfg, budget), appends(n, args.repeats)]
    h.write(args.out, "modem", results)
    print(h.markdown(results))


if __name__ == "__main__":
    main()
