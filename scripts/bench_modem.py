"""Modem link bench: bytes per result (JSON vs link encoding), results per hour, outbox append rate.

Writes a JSON file (default bench-results/modem.json) and prints a table.
Usage: python scripts/bench_modem.py [--out PATH] [--bit-rate 300] [--appends 2000]
"""

from __future__ import annotations

import argparse
import json
import math
import tempfile
import time
from pathlib import Path
from typing import Any

import msgspec

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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--out", type=Path, default=Path("bench-results/modem.json"))
    ap.add_argument("--bit-rate", type=float, default=300.0)
    ap.add_argument("--bytes-per-hour", type=int, default=0, help="0: the link's capacity")
    ap.add_argument("--appends", type=int, default=2000)
    args = ap.parse_args()
    cfg = ModemConfig(bit_rate=args.bit_rate, bytes_per_hour=args.bytes_per_hour)
    capacity = cfg.bit_rate / BITS_PER_BYTE * 3600
    budget = min(capacity, cfg.bytes_per_hour) if cfg.bytes_per_hour else capacity
    codec = LinkCodec(cfg.labels)
    rows = {}
    print(f"link {cfg.bit_rate:g} bit/s = {capacity:.0f} B/h; budget {budget:.0f} B/h; "
          f"frames up to {cfg.max_frame_payload} B payload")  # fmt: skip
    print(
        f"{'kind':<10} {'json B':>7} {'link B':>7} {'ratio':>6} {'on air B':>9} {'results/h':>10}"
    )
    for kind, rec in SAMPLES.items():
        js = len(msgspec.json.encode(rec)) + 1  # one JSON line
        link = len(codec.encode(rec))
        air = on_air(link, cfg)
        rows[kind] = {"json_bytes": js, "link_bytes": link, "ratio": round(js / link, 2),
                      "on_air_bytes": round(air, 1), "results_per_hour": int(budget / air),
                      "json_results_per_hour": int(budget / js)}  # fmt: skip
        r = rows[kind]
        print(
            f"{kind:<10} {js:>7} {link:>7} {r['ratio']:>6} {air:>9.1f} {r['results_per_hour']:>10}"
        )
    rates = {
        "fsync_interval_1s": append_rate(args.appends, 1.0),
        "fsync_every_append": append_rate(max(50, args.appends // 10), 1e-9),
    }
    for name, r in rates.items():
        print(
            f"outbox append, {name}: {r['appends_per_s']:.0f}/s ({r['fsyncs']} fsyncs, n={r['n']})"
        )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    result = {
        "bit_rate": cfg.bit_rate,
        "budget_bytes_per_hour": budget,
        "max_frame_payload": cfg.max_frame_payload,
        "per_kind": rows,
        "outbox": rates,
    }
    args.out.write_text(json.dumps(result, indent=2))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
