"""MOTChallenge text files: read detections or tracks (`frame,id,x,y,w,h,conf,...`), the
frame rate from seqinfo.ini, write tracks; and `track_file`, the tracker over one file, with
the interval counts a live run writes (visits, MaxN and dwell per label, the label being the
MOT class column, trapflow.tracking.counts).

`track_file` streams: rows are read one line at a time, frames go to the tracker in frame
order through a bounded reorder window (trapflow.tracking.frame_window) and each frame's
tracked rows are written as soon as it is tracked, so its memory is that of the window and
the live tracks, whatever the file's size. With a re-link pass
(trapflow.tracking.relink), each frame's rows are held for the pass's longest gap plus the
tracker's `max_gap_s` before they are written, so that a track joined to an earlier one is
written with the earlier one's id: memory is then that of the frames held too. Its outputs
are written beside their names as NAME.part and renamed when whole: a failure leaves no
half file and no earlier file replaced."""

from __future__ import annotations

import configparser
import io
import math
import os
from collections import deque
from collections.abc import Callable, Generator, Iterable, Iterator, Sequence
from contextlib import ExitStack, closing
from pathlib import Path
from typing import IO, NamedTuple

import msgspec

from trapflow.errors import TrapflowError
from trapflow.tracking.counts import DEFAULT_INTERVAL_S, Counter, IntervalCounts
from trapflow.tracking.frame_window import DEFAULT_FRAMES, FrameOrderError, FrameWindow
from trapflow.tracking.relink import RelinkConfig, Relinker
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
    tracks: int  # ids written (a re-linked track is one)
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


# A MOT row is well under 200 characters: a longer line is no row, and reading it whole
# would cost the memory streaming bounds.
MAX_LINE_CHARS = 1 << 20


class MotStream:
    """The rows of a MOTChallenge text file one at a time, in file order; bytes_read() says
    how far it has come (for progress)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._file: io.TextIOWrapper | None = None
        self._raw: io.BufferedReader | None = None
        self.done = False

    def total_bytes(self) -> int:
        """The file's size, 0 when it cannot be read (rows() then says why)."""
        try:
            return self.path.stat().st_size
        except OSError:
            return 0

    def bytes_read(self) -> int:
        """Bytes taken from the file so far (read ahead by at most a buffer)."""
        if self._raw is None:
            return self.total_bytes() if self.done else 0
        return self._raw.tell()

    def rows(self) -> Generator[tuple[int, MotRow], None, None]:
        """(line number, row) for every row; blank lines are skipped. Lines are cut as
        str.splitlines cuts a whole text, so line numbers are the same either way."""
        try:
            self._raw = open(self.path, "rb")  # noqa: SIM115 - closed below
        except OSError as exc:
            raise MotFormatError(f"{self.path}: cannot read: {exc}") from None
        self._file = io.TextIOWrapper(self._raw, encoding="utf-8")  # universal newlines
        n = 0
        try:
            while line := self._readline(n):
                for piece in line.splitlines():
                    n += 1
                    row = parse_line(piece, f"{self.path}:{n}")
                    if row is not None:
                        yield n, row
        finally:
            self._file.close()
            self._file, self._raw, self.done = None, None, True

    def _readline(self, n: int) -> str:
        assert self._file is not None
        try:
            line = self._file.readline(MAX_LINE_CHARS)
        except (OSError, UnicodeDecodeError) as exc:
            raise MotFormatError(f"{self.path}: cannot read after line {n}: {exc}") from None
        if len(line) >= MAX_LINE_CHARS and not line.endswith("\n"):
            raise MotFormatError(f"{self.path}:{n + 1}: expected a MOT row, got a line of "
                                 f"more than {MAX_LINE_CHARS} characters")
        return line


def read_mot(path: Path) -> list[MotRow]:
    """Every row of a MOTChallenge text file, in file order."""
    return [row for _n, row in MotStream(path).rows()]


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


class Tracked(NamedTuple):
    """What one frame gave: the rows with a track id of the frames it let out (without a
    re-link pass, its own; with one, those held long enough), in frame order and each
    frame's in its order; the detections past max_boxes, and the counting intervals it
    closed (the counts are the tracker's, before any re-link)."""

    rows: list[MotRow]
    capped: int
    counts: list[IntervalCounts]


class FrameTracker:
    """The tracker over one sequence's frames, fed in increasing frame order (time =
    (frame - 1) / fps), pure; with `count`, the closed intervals of `interval_s` seconds,
    counted as a live run counts them (the frames with a detection are the effort; a
    track's label is the majority of its rows' class column, `NO_CLASS_LABEL` where there
    is none). With `relink`, rows come out through the re-link pass, later (Tracked). Its
    totals grow as it goes; its memory is the live tracks' and the frames held."""

    def __init__(self, fps: float, config: TrackerConfig | None = None, count: bool = True,
                 interval_s: float = DEFAULT_INTERVAL_S,
                 relink: RelinkConfig | None = None) -> None:
        self.fps = fps
        self._tracker = Tracker(config)
        self._relinker = None if relink is None else Relinker(relink)
        # Rows wait this long: every track that may join one of them has then begun and
        # every track they may join has ended (the tracker ends one max_gap_s after its
        # last box).
        self._hold_s = 0.0 if relink is None else (
            relink.max_gap_s + self._tracker.config.max_gap_s)
        self._held: deque[tuple[float, list[MotRow]]] = deque()
        self._counter = Counter(interval_s) if count else None
        self._t_s: float | None = None
        self._live: set[int] = set()  # ids written and not yet ended
        self.frames = self.detections = self.tracked = self.tracks = self.capped = 0

    def feed(self, frame: int, rows: Sequence[MotRow]) -> Tracked:
        """One frame's detection rows (after every earlier frame's)."""
        t_s = self._t_s = (frame - 1) / self.fps
        upd = self._tracker.update(t_s, [
            Det(label=str(r.cls) if r.cls >= 0 else NO_CLASS_LABEL, confidence=r.conf,
                box=(r.x, r.y, r.x + r.w, r.y + r.h)) for r in rows])
        counts: list[IntervalCounts] = []
        if self._counter is not None:
            counts = self._counter.ended(upd.ended) + self._counter.observe(t_s, upd.seen)
        self._live.difference_update(e.id for e in upd.ended)
        out = [msgspec.structs.replace(r, id=tid)
               for r, tid in zip(rows, upd.track_ids, strict=True) if tid is not None]
        new = {r.id for r in out} - self._live
        self._live |= new
        self.tracks += len(new)
        self.frames += 1
        self.detections += len(rows)
        self.tracked += len(out)
        self.capped += upd.capped
        return Tracked(self._relinked(t_s, out), upd.capped, counts)

    def finish(self) -> Tracked:
        """End every track at the last frame: the rows still held, the intervals still
        open or waiting."""
        if self._t_s is None:
            return Tracked([], 0, [])
        t_s = self._t_s
        ended = self._tracker.flush(t_s)
        rows = self._relinked(math.inf, [])
        if self._relinker is not None:
            self.tracks -= self._relinker.joins
        if self._counter is None:
            return Tracked(rows, 0, [])
        return Tracked(rows, 0, self._counter.ended(ended) + self._counter.flush(t_s))

    def _relinked(self, t_s: float, rows: list[MotRow]) -> list[MotRow]:
        """Without a re-link pass, rows; with one, the rows held hold_s or more, ids
        rewritten (t_s inf: every row held)."""
        if self._relinker is None:
            return rows
        self._relinker.add(t_s, [(r.id, str(r.cls) if r.cls >= 0 else NO_CLASS_LABEL,
                                  (r.x, r.y, r.x + r.w, r.y + r.h)) for r in rows])
        self._held.append((t_s, rows))
        horizon = t_s - self._hold_s
        self._relinker.decide(horizon)
        out: list[MotRow] = []
        while self._held and self._held[0][0] <= horizon:
            out += [r if (i := self._relinker.id(r.id)) == r.id
                    else msgspec.structs.replace(r, id=i) for r in self._held.popleft()[1]]
        return out


def track_rows(rows: Sequence[MotRow], fps: float, config: TrackerConfig | None = None,
               capped: list[int] | None = None, counts: list[IntervalCounts] | None = None,
               interval_s: float = DEFAULT_INTERVAL_S,
               relink: RelinkConfig | None = None) -> list[MotRow]:
    """The tracker over detection rows in memory, in any order (FrameTracker over them
    sorted by frame): the rows it gave an id. `capped`, when given, gets the detections
    each frame left out (past max_boxes); `counts` the closed intervals; `relink`: through
    the re-link pass."""
    by_frame: dict[int, list[MotRow]] = {}
    for r in rows:
        by_frame.setdefault(r.frame, []).append(r)
    ft = FrameTracker(fps, config, counts is not None, interval_s, relink)
    out = []
    for frame in sorted(by_frame):
        got = ft.feed(frame, by_frame[frame])
        if capped is not None and got.capped:
            capped.append(got.capped)
        if counts is not None:
            counts += got.counts
        out += got.rows
    last = ft.finish()
    if counts is not None:
        counts += last.counts
    return out + last.rows


def write_counts(path: Path, counts: Iterable[IntervalCounts]) -> None:
    """Interval counts as a live run's counts.jsonl: one `{"counts": {...}}` a line."""
    path.write_bytes(b"".join(_count_line(c) for c in counts))


def _count_line(c: IntervalCounts) -> bytes:
    return msgspec.json.encode({"counts": c}) + b"\n"


class ReadProgress(NamedTuple):
    """How far track_file has come: bytes of the detections file read, of its size; frames
    and detections tracked."""

    bytes_read: int
    total_bytes: int
    frames: int
    detections: int


def track_file(det_path: Path, out_path: Path, fps: float | None = None,
               config: TrackerConfig | None = None, counts_path: Path | None = None,
               interval_s: float = DEFAULT_INTERVAL_S,
               progress: Callable[[ReadProgress], None] | None = None,
               window: int = DEFAULT_FRAMES, relink: RelinkConfig | None = None
               ) -> TrackSummary:
    """Track a MOT detection file into a MOT track file (rows by frame, then id); fps None:
    from seqinfo.ini. With `counts_path`, the interval counts too (times in seconds from
    the first frame). Streams (the module's docstring): a row may come at most `window`
    frames after a later frame's; `progress` is told after each frame; `relink`: ids
    rewritten by the re-link pass (without it, or when it joins nothing, the same file)."""
    if fps is None:
        fps = read_fps(det_path)
    if not fps > 0:
        raise MotFormatError(f"fps: expected more than 0, got {fps}")
    if not MIN_FPS <= fps <= MAX_FPS:
        raise MotFormatError(f"fps: expected {MIN_FPS:g} to {MAX_FPS:g}, got {fps:g}")
    stream = MotStream(det_path)
    total = stream.total_bytes()
    ft = FrameTracker(fps, config, counts_path is not None, interval_s, relink)
    order: FrameWindow[MotRow] = FrameWindow(window)
    intervals = 0
    paths = [out_path] if counts_path is None else [out_path, counts_path]
    with _Published(paths) as files, closing(stream.rows()) as rows:
        for frames in _frames(rows, order, det_path):
            for frame, dets in frames:
                intervals += _write(files, ft.feed(frame, dets))
                if progress is not None:
                    progress(ReadProgress(stream.bytes_read(), total, ft.frames,
                                          ft.detections))
        intervals += _write(files, ft.finish())
    return TrackSummary(frames=ft.frames, detections=ft.detections, tracked=ft.tracked,
                        tracks=ft.tracks, fps=fps, capped=ft.capped, intervals=intervals)


def _write(files: list[IO[bytes]], got: Tracked) -> int:
    """A Tracked's rows (by frame, then id) and counts (files[1], where given); the number
    of counting intervals written."""
    files[0].write("".join(format_row(r) + "\n" for r in
                           sorted(got.rows, key=lambda r: (r.frame, r.id))).encode())
    if len(files) > 1:
        files[1].write(b"".join(_count_line(c) for c in got.counts))
    return len(got.counts)


def _frames(rows: Iterator[tuple[int, MotRow]], order: FrameWindow[MotRow], where: Path
            ) -> Iterator[list[tuple[int, list[MotRow]]]]:
    """The frames that leave the window as rows come, then those left at the end; a row
    too late for its frame is an error naming its line."""
    for n, row in rows:
        try:
            gone = order.add(row.frame, row)
        except FrameOrderError as exc:
            raise MotFormatError(f"{where}:{n}: {exc}") from None
        if gone:
            yield gone
    yield order.drain()


class _Published:
    """Files written as NAME.part beside their names, renamed onto them when the block
    ends without an error; removed when it ends with one."""

    def __init__(self, paths: list[Path]) -> None:
        self.paths = paths
        self.parts = [p.with_name(p.name + ".part") for p in paths]
        self._stack = ExitStack()

    def __enter__(self) -> list[IO[bytes]]:
        try:
            return [self._stack.enter_context(open(part, "wb")) for part in self.parts]
        except OSError as exc:
            self._stack.close()
            self._remove()
            raise MotFormatError(f"cannot write {exc.filename}: {exc.strerror}") from None

    def __exit__(self, kind: type[BaseException] | None, *_: object) -> None:
        try:
            self._stack.close()
            if kind is None:
                for part, path in zip(self.parts, self.paths, strict=True):
                    os.replace(part, path)
        except OSError as exc:
            self._remove()
            raise MotFormatError(f"cannot write {exc.filename}: {exc.strerror}") from None
        if kind is not None:
            self._remove()

    def _remove(self) -> None:
        for part in self.parts:
            part.unlink(missing_ok=True)
