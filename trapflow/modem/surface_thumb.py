"""The surface's thumbnails: the `thumb` packets of a track (trapflow.modem.thumb) back
into one JPEG per track, in a folder beside the surface's output.

Each packet that arrives (once: the receiver drops retransmissions) is appended to
`SESSION-TRACK.parts` (one JSON line per packet, so a restart of the surface keeps what
came before) and the track's `SESSION-TRACK.jpg` is written again, whole, from every
packet received so far: the segments of packets not (yet) received are flat grey, so the
picture decodes from any subset. The outbox session names the file, as track ids start
again in a fresh outbox.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

from trapflow.modem import thumb
from trapflow.runtime.files import write_atomically

log = logging.getLogger(__name__)


class Thumbnails:
    """Packets in, one JPEG per (session, track) out, in `folder` (named in lines as
    `name/FILE`, `name` the folder's own name)."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        self.written = 0  # JPEGs written (one per packet received)
        self.bad = 0  # packets that were no thumbnail, or did not decode

    def add(self, session: bytes, body: dict[str, Any]) -> dict[str, Any]:
        """One received `thumb` record's body: stored, the track's JPEG rewritten; the
        output line's body (the record without its bytes, with `file`, the segments
        received and of how many), or the record with `error` when it is no packet."""
        line = {k: v for k, v in body.items() if k != "data"}
        try:
            track, packet = thumb.from_record(body)
        except ValueError as exc:
            self.bad += 1
            log.warning("thumbnail packet dropped: %s", exc)
            return {**line, "error": str(exc)}
        stem = f"{session.hex()}-{track}"
        parts = self.folder / f"{stem}.parts"
        try:
            self.folder.mkdir(parents=True, exist_ok=True)
            with open(parts, "a", encoding="utf-8") as fh:
                fh.write(json.dumps(body) + "\n")
            packets = self._read(parts)
            key = (packet.width, packet.height, packet.quality, packet.colour, packet.interval)
            same = [p for p in packets if (p.width, p.height, p.quality, p.colour,
                                            p.interval) == key]
            write_atomically(self.folder / f"{stem}.jpg",
                             thumb.assemble(same, thumb.total_segments(packet)))
        except (OSError, ValueError) as exc:
            self.bad += 1
            log.warning("thumbnail of track %d not written: %s", track, exc)
            return {**line, "error": str(exc)}
        self.written += 1
        return {**line, "file": f"{self.folder.name}/{stem}.jpg",
                "segments": sum(thumb.segment_count(p) for p in same),
                "of": thumb.total_segments(packet)}

    @staticmethod
    def _read(parts: Path) -> list[thumb.Packet]:
        """The packets stored for one track, each once (a line written again after a
        restart of the surface counts once)."""
        got: dict[int, thumb.Packet] = {}
        for text in parts.read_text(encoding="utf-8").splitlines():
            try:
                _, p = thumb.from_record(json.loads(text))
            except (ValueError, TypeError) as exc:  # a line cut by a power cut
                log.debug("thumbnail part skipped: %s", exc)
                continue
            got[p.first] = p
        return list(got.values())
