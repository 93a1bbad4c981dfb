"""`trapflow track`: link detections from any detector into tracks, in MOTChallenge files,
and count them per interval as a live run does (counts.jsonl lines)."""

from __future__ import annotations

from pathlib import Path

import click

from trapflow.cli.exit import bad_input
from trapflow.config.schema import ObserveConfig
from trapflow.errors import TrapflowError
from trapflow.tracking.motformat import track_file
from trapflow.tracking.stage import tracker_config


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
def track(detections: Path, out: Path, fps: float | None, max_boxes: int,
          counts: Path | None, interval_s: float) -> None:
    """Track DETECTIONS (MOTChallenge `frame,-1,x,y,w,h,conf[,class]`) into tracks with
    ids, with the tracker of a live run (observe defaults), and write the counts a live
    run writes. MaxN is the most confirmed tracks of one class at one frame."""
    counts = counts or out.with_name(out.stem + ".counts.jsonl")
    try:
        summary = track_file(detections, out, fps,
                             tracker_config(ObserveConfig(max_boxes=max_boxes)),
                             counts_path=counts, interval_s=interval_s)
    except TrapflowError as exc:
        raise bad_input(exc) from None
    click.echo(f"{summary.detections} detections in {summary.frames} frames at "
               f"{summary.fps:g} fps: {summary.tracks} tracks, {summary.tracked} detections "
               f"tracked -> {out}; {summary.intervals} counting intervals -> {counts}")
    if summary.capped:  # once for the whole file, not per frame
        click.echo(f"{summary.capped} detections not tracked: past the {max_boxes} most "
                   "confident of their frame (--max-boxes)")


COMMANDS = (track,)
