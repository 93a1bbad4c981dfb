"""Test helper process: appends results to an outbox as the normalizer would, logging each seq.

Usage: python modem_writer.py OUTBOX ACKLOG RUN. A line `seq id` is written to ACKLOG once
append() has returned for the record whose "seq" field is id (RUN * 100000 + i).
"""

from __future__ import annotations

import sys
import time

from trapflow.config.modem import OutboxConfig
from trapflow.modem.outbox import Outbox


def record(ident: int) -> dict[str, object]:
    """The record with this id: its content is derived from the id, so damage shows."""
    if ident % 2:
        return {
            "stereo_ir": {
                "timestamp": "2025-07-07 12:52:43.120",
                "seq": ident,
                "label": "scallop",
                "confidence": round((ident % 200) / 200, 3),
            }
        }
    return {
        "mono_ir": {
            "timestamp": "2025-07-07 12:52:43.120",
            "seq": ident,
            "label": "crab",
            "confidence": 0.5,
            "box": [float(ident % 640), 7.8, 600.0, 18.1],
        }
    }


def main() -> None:
    path, acklog, run = sys.argv[1], sys.argv[2], int(sys.argv[3])
    box = Outbox(path, OutboxConfig(fsync_interval_s=0.2))
    with open(acklog, "a", buffering=1) as log:
        for i in range(100000):
            ident = run * 100000 + i
            seq = box.append(record(ident))
            log.write(f"{seq} {ident}\n")
            time.sleep(0.03)  # the pace of results from the pipeline


if __name__ == "__main__":
    main()
