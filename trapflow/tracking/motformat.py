"""MOTChallenge text files: read detections or tracks (`frame,id,x,y,w,h,conf,...`), the
frame rate from seqinfo.ini, write tracks; and `track_file`, the tracker over one file, with
the interval counts a live run writes (visits, MaxN and dwell per label, the label being the
MOT class column, trapflow.tracking.counts)."""

from __future__ import annotations

import configparser
import math
from collections.abc import Iterable, Sequence
from pathlib import Path

import msgspec

from trapflow.errors import TrapflowError
from trapflow.tracking.counts import DEFAULT_INTERVAL_S, Counter, IntervalCounts
from trapflow.tracking.tracker import Det, Tracker, TrackerConfig

# A MOT row's class column (8th) when it names none: detection files put -1 there.
NO_CLASS_LABEL = "object"


class MotFormatError(TrapflowError):
    """A MOTChallenge file or its seqinfo.ini cannot be read; the message names file and line."""


class MotRow(msgspec.Struct, frozen=True, kw_only=True):
    """One line: frame (from 1), id (-1 for a detection), box left, top, width, height."""

    frame: int
    id: int
    x: float
    y: float
    w: float
    h: float
    conf: float = 1.0
    cls: int = -1  # the 8th column where the file has one (MOT ground truth), else -1


class TrackSummary(msgspec.Struct, frozen=True, kw_only=True):
    """What track_file did."""

    frames: int  # frames with at least one detection
    detections: int
    tracked: int  # detections written with a track id
    tracks: int
    fps: float
    capped: int = 0  # detections past the tracker's max_boxes in their frame: not tracked
    intervals: int = 0  # counting intervals written


# Bounds of a row's fields: far past any real sequence, near enough that the tracker's
# times and boxes stay well inside a float's range (a frame of 1e300 was an OverflowError
# traceback, boxes of 1e308 pixels numpy overflow warnings and exit 0: issue 36 item 8).
MAX_FRAME = 10**9  # frames (and track ids)
MAX_PIXELS = 1e7  # |x|, |y|, w and h, in pixels
MAX_CONF = 1e6  # |conf| (a detector's raw score may exceed 1)
MIN_FPS, MAX_FPS = 1e-3, 1e6


def _number(text: str, what: str, where: str, bound: float = math.inf) -> float:
    try:
        value = float(text)
    except ValueError:
        raise MotFormatError(f"{where}: {what}: expected a number, got {text!r}") from None
    if not math.isfinite(value):
        raise MotFormatError(f"{where}: {what}: expected a finite number, got {text!r}")
    if abs(value) > bound:
        raise MotFormatError(f"{where}: {what}: expected a number from {-bound:g} to "
                             f"{bound:g}, got {text!r}")
    return value


def _integer(text: str, what: str, where: str, bound: int = MAX_FRAME) -> int:
    value = _number(text, what, where, bound)
    if value != int(value):
        raise MotFormatError(f"{where}: {what}: expected a whole number, got {text!r}")
    return int(value)


def parse_line(line: str, where: str) -> MotRow | None:
    """One row, or None for a blank line; `where` is `FILE:LINE` for the error."""
    text = line.strip()
    if not text:
        return None
    cols = [c.strip() for c in text.split(",")]
    if len(cols) < 6:
        raise MotFormatError(f"{where}: expected frame,id,x,y,w,h[,conf,...] "
                             f"(at least 6 comma-separated columns), got {text!r}")
    frame = _integer(cols[0], "frame", where)
    if frame < 1:
        raise MotFormatError(f"{where}: frame: expected 1 or more, got {cols[0]!r}")
    tid = _integer(cols[1], "id", where)
    x, y, w, h = (_number(c, n, where, MAX_PIXELS)
                  for c, n in zip(cols[2:6], "xywh", strict=True))
    if w <= 0 or h <= 0:
        raise MotFormatError(f"{where}: expected a box of positive width and height, "
                             f"got w={cols[4]} h={cols[5]}")
    conf = _number(cols[6], "conf", where, MAX_CONF) if len(cols) > 6 else 1.0
    cls = _integer(cols[7], "class", where) if len(cols) > 7 else -1
    return MotRow(frame=frame, id=tid, x=x, y=y, w=w, h=h, conf=conf, cls=cls)


def read_mot(path: Path) -> list[MotRow]:
    """Every row of a MOTChallenge text file, in file order."""
    try:
        lines = path.read_text().splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise MotFormatError(f"{path}: cannot read: {exc}") from None
    rows = []
    for n, line in enumerate(lines, 1):
        row = parse_line(line, f"{path}:{n}")
        if row is not None:
            rows.append(row)
    return rows


def read_fps(path: Path) -> float:
    """frameRate from the seqinfo.ini beside a MOT file or one folder up (SEQ/det/det.txt
    has SEQ/seqinfo.ini)."""
    for folder in (path.parent, path.parent.parent):
        ini = folder / "seqinfo.ini"
        if ini.is_file():
            break
    else:
        raise MotFormatError(f"{path}: no seqinfo.ini beside it or one folder up; "
                             "give the frame rate")
    parser = configparser.ConfigParser()
    try:
        parser.read_string(ini.read_text())
        raw = parser.get("Sequence", "frameRate")
    except (OSError, configparser.Error) as exc:
        raise MotFormatError(f"{ini}: expected [Sequence] frameRate=N, got: {exc}") from None
    fps = _number(raw, "[Sequence] frameRate", str(ini))
    if fps <= 0:
        raise MotFormatError(f"{ini}: [Sequence] frameRate: expected more than 0, got {raw!r}")
    return fps


def format_row(row: MotRow) -> str:
    """A row as MOTChallenge writes tracker output: frame,id,x,y,w,h,conf,-1,-1,-1."""
    return (f"{row.frame},{row.id},{row.x:.2f},{row.y:.2f},{row.w:.2f},{row.h:.2f},"
            f"{row.conf:.4g},-1,-1,-1")


def write_mot(path: Path, rows: Iterable[MotRow]) -> None:
    """Write rows sorted by frame then id (the order MOT tools expect)."""
    ordered = sorted(rows, key=lambda r: (r.frame, r.id))
    path.write_text("".join(format_row(r) + "\n" for r in ordered))


def track_rows(rows: Sequence[MotRow], fps: float, config: TrackerConfig | None = None,
               capped: list[int] | None = None, counts: list[IntervalCounts] | None = None,
               interval_s: float = DEFAULT_INTERVAL_S) -> list[MotRow]:
    """The tracker over detection rows (time = (frame - 1) / fps): the rows it gave an id.
    `capped`, when given, gets the detections each frame left out (past max_boxes);
    `counts` the closed intervals of `interval_s` seconds, counted as a live run counts
    them (the frames with a detection are the effort; a track's label is the majority of
    its rows' class column, `NO_CLASS_LABEL` where there is none)."""
    by_frame: dict[int, list[MotRow]] = {}
    for r in rows:
        by_frame.setdefault(r.frame, []).append(r)
    tracker = Tracker(config)
    counter = Counter(interval_s) if counts is not None else None
    out = []
    t_s = 0.0
    for frame in sorted(by_frame):
        dets = by_frame[frame]
        t_s = (frame - 1) / fps
        upd = tracker.update(t_s, [
            Det(label=str(r.cls) if r.cls >= 0 else NO_CLASS_LABEL, confidence=r.conf,
                box=(r.x, r.y, r.x + r.w, r.y + r.h)) for r in dets])
        if capped is not None and upd.capped:
            capped.append(upd.capped)
        if counter is not None and counts is not None:
            counts += counter.ended(upd.ended) + counter.observe(t_s, upd.seen)
        out += [msgspec.structs.replace(r, id=tid)
                for r, tid in zip(dets, upd.track_ids, strict=True) if tid is not None]
    if counter is not None and counts is not None and by_frame:
        counts += counter.ended(tracker.flush(t_s)) + counter.flush(t_s)
    return out


def write_counts(path: Path, counts: Iterable[IntervalCounts]) -> None:
    """Interval counts as a live run's counts.jsonl: one `{"counts": {...}}` a line."""
    path.write_bytes(b"".join(msgspec.json.encode({"counts": c}) + b"\n" for c in counts))


def track_file(det_path: Path, out_path: Path, fps: float | None = None,
               config: TrackerConfig | None = None, counts_path: Path | None = None,
               interval_s: float = DEFAULT_INTERVAL_S) -> TrackSummary:
    """Track a MOT detection file into a MOT track file; fps None: from seqinfo.ini. With
    `counts_path`, the interval counts too (times in seconds from the first frame)."""
    if fps is None:
        fps = read_fps(det_path)
    if not fps > 0:
        raise MotFormatError(f"fps: expected more than 0, got {fps}")
    if not MIN_FPS <= fps <= MAX_FPS:
        raise MotFormatError(f"fps: expected {MIN_FPS:g} to {MAX_FPS:g}, got {fps:g}")
    rows = read_mot(det_path)
    capped: list[int] = []
    counts: list[IntervalCounts] = []
    tracked = track_rows(rows, fps, config, capped, counts, interval_s)
    write_mot(out_path, tracked)
    if counts_path is not None:
        write_counts(counts_path, counts)
    return TrackSummary(frames=len({r.frame for r in rows}), detections=len(rows),
                        tracked=len(tracked), tracks=len({r.id for r in tracked}), fps=fps,
                        capped=sum(capped), intervals=len(counts))
