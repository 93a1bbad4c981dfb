"""`trapflow track`: link detections from any detector into tracks, in MOTChallenge files,
and count them per interval as a live run does (counts.jsonl lines)."""

from __future__ import annotations

import time
from pathlib import Path

import click

from trapflow.cli.exit import bad_input
from trapflow.cli.outputs import In, Out, check_outputs, force_option
from trapflow.config.schema import ObserveConfig
from trapflow.errors import TrapflowError
from trapflow.tracking.motformat import ReadProgress, track_file
from trapflow.tracking.relink import RelinkConfig
from trapflow.tracking.stage import tracker_config

PROGRESS_EVERY_S = 5.0  # a long file says how far it has come this often, on stderr
# Off by default: it helped crocea and the development seeds, not the held-out synthetic
# worlds (docs/benchmarks.md, "Tracking").
RELINK_DEFAULT = False


def progress_line(p: ReadProgress, elapsed_s: float) -> str:
    """One progress line of `trapflow track`."""
    share = f" ({100 * p.bytes_read / p.total_bytes:.0f} %)" if p.total_bytes else ""
    return (f"track: {p.bytes_read / 1e6:.1f} of {p.total_bytes / 1e6:.1f} MB read{share}, "
            f"{p.frames} frames, {p.detections} detections, {elapsed_s:.0f} s")


class _Progress:
    """Says on stderr how far track_file has come, every PROGRESS_EVERY_S (monotonic)."""

    def __init__(self) -> None:
        self.t0 = time.monotonic()
        self.due = self.t0 + PROGRESS_EVERY_S

    def __call__(self, p: ReadProgress) -> None:
        now = time.monotonic()
        if now >= self.due:
            self.due = now + PROGRESS_EVERY_S
            click.echo(progress_line(p, now - self.t0), err=True)


@click.command("track")
@click.argument("detections", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option("-o", "--out", "out", required=True,
              type=click.Path(dir_okay=False, writable=True, path_type=Path),
              help="Tracks in MOTChallenge format (frame,id,x,y,w,h,conf,...).")
@click.option("--fps", type=click.FloatRange(min=0, min_open=True), default=None,
              help="Frame rate of the sequence (default: seqinfo.ini beside the file).")
@click.option("--max-boxes", type=click.IntRange(min=1, max=100_000),
              default=ObserveConfig().max_boxes, show_default=True,
              help="Most detections of one frame tracked, the most confident "
                   "(observe.max_boxes).")
@click.option("--counts", "counts", default=None,
              type=click.Path(dir_okay=False, writable=True, path_type=Path),
              help="Interval counts, a live run's counts.jsonl lines: visits, MaxN and "
                   "dwell per class (the MOT class column) [default: OUT with the suffix "
                   ".counts.jsonl].")
@click.option("--interval", "interval_s", type=click.FloatRange(min=0, min_open=True),
              default=ObserveConfig().interval_s, show_default=True,
              help="Seconds per counting interval, from the first frame (observe.interval_s).")
@click.option("--relink/--no-relink", default=RELINK_DEFAULT, show_default=True,
              help="Join a track that ended to one that began at most --relink-gap seconds "
                   "later where its motion led, same class (its rows are written with the "
                   "first one's id; the counts are the tracker's).")
@click.option("--relink-gap", "relink_gap_s", type=click.FloatRange(min=0, min_open=True),
              default=RelinkConfig().max_gap_s, show_default=True,
              help="Longest gap, in seconds, between two tracks the re-link pass joins.")
@force_option()
def track(detections: Path, out: Path, fps: float | None, max_boxes: int,
          counts: Path | None, interval_s: float, relink: bool, relink_gap_s: float,
          force: bool) -> None:
    """Track DETECTIONS (MOTChallenge `frame,-1,x,y,w,h,conf[,class]`, sorted by frame;
    a row may come up to 64 frames late) into tracks with ids, with the tracker of a live
    run (observe defaults), and write the counts a live run writes. MaxN is the most
    confirmed tracks of one class at one frame. Streams: memory does not grow with the
    file; a long one says how far it has come on stderr."""
    counts = counts or out.with_name(out.stem + ".counts.jsonl")
    check_outputs("track", [
        Out(out, "-o"), Out(counts, "--counts"),
        *(Out(p.with_name(p.name + ".part"), f"{flag} (written first as)", scratch=True)
          for p, flag in ((out, "-o"), (counts, "--counts")))],
        [In(detections, "DETECTIONS"),
         *(In(d / "seqinfo.ini", "its seqinfo.ini") for d in
           ((detections.parent, detections.parent.parent) if fps is None else ()))],
        force)
    try:
        summary = track_file(detections, out, fps,
                             tracker_config(ObserveConfig(max_boxes=max_boxes)),
                             counts_path=counts, interval_s=interval_s,
                             progress=_Progress(),
                             relink=RelinkConfig(max_gap_s=relink_gap_s) if relink else None)
    except TrapflowError as exc:
        raise bad_input(exc) from None
    click.echo(f"{summary.detections} detections in {summary.frames} frames at "
               f"{summary.fps:g} fps: {summary.tracks} tracks, {summary.tracked} detections "
               f"tracked -> {out}; {summary.intervals} counting intervals -> {counts}")
    if summary.capped:  # once for the whole file, not per frame
        click.echo(f"{summary.capped} detections not tracked: past the {max_boxes} most "
                   "confident of their frame (--max-boxes)")


COMMANDS = (track,)
