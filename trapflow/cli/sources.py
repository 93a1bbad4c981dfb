"""Click commands for sources and recordings: calibrate, record, replay.

Thin: each parses its options, then calls one library function.
"""

from __future__ import annotations

import contextlib
import tempfile
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import click
import msgspec

from trapflow.calibration.camera import StereoRig
from trapflow.cli.exit import CommandFailed, bad_input, failed
from trapflow.cli.outputs import In, Out, check_outputs, force_option
from trapflow.config import schema as configmod
from trapflow.errors import ConfigError, TrapflowError
from trapflow.runtime.signals import stop_on_signals
from trapflow.wire.messages import PoolStats, Stats

if TYPE_CHECKING:
    from trapflow.config.schema import Config


class PatternType(click.ParamType[tuple[int, int]]):
    """COLSxROWS inner corners of a checkerboard."""

    name = "COLSxROWS"

    def convert(self, value: Any, param: click.Parameter | None,
                ctx: click.Context | None) -> tuple[int, int]:
        if isinstance(value, tuple):
            return value
        from trapflow.calibration.calibrate import parse_pattern

        try:
            return parse_pattern(str(value))
        except ValueError as exc:
            self.fail(str(exc), param, ctx)


class WorkersType(click.ParamType[dict[str, int]]):
    """`NAME=COUNT[,NAME=COUNT...]`, rejected with click's usage error when malformed."""

    name = "NAME=COUNT[,...]"

    def convert(self, value: Any, param: click.Parameter | None,
                ctx: click.Context | None) -> dict[str, int]:
        if isinstance(value, dict):
            return value
        try:
            return configmod.parse_workers(str(value))
        except ConfigError as exc:
            self.fail(str(exc), param, ctx)


class SizeType(click.ParamType[tuple[int, int]]):
    """`WIDTHxHEIGHT`."""

    name = "WxH"

    def convert(self, value: Any, param: click.Parameter | None,
                ctx: click.Context | None) -> tuple[int, int]:
        if isinstance(value, tuple):
            return value
        w, sep, h = str(value).lower().partition("x")
        if not sep or not w.isdigit() or not h.isdigit():
            self.fail(f"expected WIDTHxHEIGHT such as 1280x720, got {value!r}", param, ctx)
        return int(w), int(h)


class SourceSpecType(click.ParamType[tuple[str, str]]):
    """KIND:ARGS, e.g. video:left.mp4,right.mp4."""

    name = "KIND:ARGS"

    def convert(self, value: Any, param: click.Parameter | None,
                ctx: click.Context | None) -> tuple[str, str]:
        if isinstance(value, tuple):
            return value
        from trapflow.sources.spec import parse_source_spec

        try:
            return parse_source_spec(str(value))
        except TrapflowError as exc:
            self.fail(str(exc), param, ctx)


@click.command()
@click.argument("left_glob")
@click.argument("right_glob")
@click.option("--pattern", type=PatternType(), default="9x6", show_default=True,
              help="Inner corners per row x per column.")
@click.option("--square", type=click.FloatRange(min=0, min_open=True), default=0.025,
              show_default=True, help="Side of one square in metres.")
@click.option("--model", type=click.Choice(["pinhole", "rational", "fisheye"]),
              default="pinhole", show_default=True,
              help="Lens model: pinhole (k1 k2 p1 p2), rational (OpenCV's stereo_calib "
                   "sample: joint fit, k1 k2 k6), fisheye (equidistant k1..k4).")
@click.option("-o", "--output", type=click.Path(dir_okay=False, path_type=Path),
              default=Path("calib.yaml"), show_default=True)
@click.option("--camera-info", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="Also write a ROS camera_info pair, left.yaml and right.yaml, in this folder.")
@force_option()
def calibrate(left_glob: str, right_glob: str, pattern: tuple[int, int], square: float,
              model: str, output: Path, camera_info: Path | None, force: bool) -> None:
    """Stereo checkerboard calibration from LEFT_GLOB and RIGHT_GLOB image pairs."""
    from trapflow.calibration.calibrate import calibrate_stereo, expand
    from trapflow.calibration.formats import write_camera_info
    from trapflow.calibration.model import save_calibration

    lefts, rights = expand(left_glob), expand(right_glob)
    outs = [Out(output, "-o"), Out(output.with_name(output.name + ".tmp"), "-o", scratch=True)]
    if camera_info is not None:
        outs += [Out(camera_info / name, "--camera-info", makes_folder=True)
                 for name in ("left.yaml", "right.yaml")]
    check_outputs("calibrate", outs, [*(In(p, "LEFT_GLOB") for p in lefts),
                                      *(In(p, "RIGHT_GLOB") for p in rights)], force)
    try:
        report = calibrate_stereo(lefts, rights, pattern, square, model)
    except TrapflowError as exc:  # no usable views in these images: the calibration failed
        raise failed(exc) from None
    try:
        save_calibration(report.calibration, output)
        if camera_info is not None:
            camera_info.mkdir(parents=True, exist_ok=True)
            write_camera_info(report.calibration, camera_info / "left.yaml",
                              camera_info / "right.yaml")
    except OSError as exc:
        raise bad_input(exc) from None
    c = report.calibration
    click.echo(f"RMS reprojection error: {report.rms_px:.3f} px over {len(report.used)} views")
    click.echo(f"views rejected ({len(report.rejected)}): {', '.join(report.rejected) or 'none'}")
    click.echo(f"baseline: {c.baseline_m:.4f} m, fx left {c.K1[0][0]:.1f}, right {c.K2[0][0]:.1f}")
    click.echo(f"written: {output}")
    if camera_info is not None:
        click.echo(f"written: {camera_info / 'left.yaml'}, {camera_info / 'right.yaml'}")


@click.command()
@click.option("--run-dir", type=click.Path(file_okay=False, path_type=Path),
              default=Path("runs/latest"), show_default=True,
              help="Run directory of the pipeline to attach to.")
@click.option("--endpoint", "endpoints", multiple=True,
              help="Tap endpoint, repeatable (overrides --run-dir): the broker's tap for "
                   "pairs, the normalizer's results tap for results.")
@click.option("-o", "--output", type=click.Path(dir_okay=False, path_type=Path), required=True,
              help="MCAP file to write.")
@click.option("--duration", type=click.FloatRange(min=0, min_open=True),
              help="Stop after this many seconds (default: when the pipeline ends).")
@click.option("-c", "--config", "config_path", type=click.Path(dir_okay=False), default=None,
              help="YAML config whose recording section applies (recording.vision_msgs).")
@click.option("--wait", "wait_s", type=click.FloatRange(min=0), default=30.0, show_default=True,
              help="Seconds to wait for the pipeline of --run-dir while it starts.")
@force_option()
def record(run_dir: Path, endpoints: tuple[str, ...], output: Path,
           duration: float | None, config_path: str | None, wait_s: float,
           force: bool) -> None:
    """Record image pairs and results from a running pipeline to an MCAP rosbag2 file,
    until the pipeline in --run-dir ends (its last results written), --duration or Ctrl-C.
    A pipeline still starting is waited for (--wait); a stopped one is refused."""
    from trapflow.config.schema import load
    from trapflow.recording.recorder import PART_SUFFIX
    from trapflow.recording.recorder import record as record_tap

    check_outputs("record", [
        Out(output, "-o"),
        Out(output.with_name(output.name + PART_SUFFIX), "-o",
            hint=f"a recording cut short: trapflow recover {output}{PART_SUFFIX} makes it a "
                 "valid file")],
        [In(Path(config_path), "--config")] if config_path else [], force)
    try:
        vision_msgs = load(config_path).recording.vision_msgs
    except TrapflowError as exc:
        raise bad_input(exc) from None
    rig, ended = None, None
    if not endpoints:  # pairs from the broker's tap, results from the normalizer's
        from trapflow.cli.attach import attach
        from trapflow.config.schema import Config
        from trapflow.wire.endpoints import Endpoints

        try:  # the directory itself from here on: runs/latest may move on
            found = attach(run_dir, wait_s, lambda line: click.echo(f"record: {line}",
                                                                    err=True))
        except TrapflowError as exc:
            raise bad_input(exc) from None
        run_dir = found.run_dir
        ep = Endpoints.for_run(Config().network, run_dir)
        endpoints = (ep.tap, ep.results_tap)
        rig = _status_rig(run_dir, found.status)
        ended = _pipeline_ended(run_dir)
    from trapflow.recording.recorder import RecorderError

    stop = stop_on_signals()
    until = "the pipeline ends" if ended is not None else "Ctrl-C"
    if duration is not None:
        until = f"{duration:g} s or {until}"
    click.echo(f"recording {' + '.join(endpoints)} to {output} until {until}", err=True)
    try:
        counts = record_tap(endpoints, output, stop, rig=rig, duration_s=duration, ended=ended,
                            vision_msgs=vision_msgs)
    except RecorderError as exc:  # the output cannot be written: fix -o
        raise bad_input(exc) from None
    except (TrapflowError, OSError) as exc:
        raise failed(str(exc)) from None
    per_algo = ", ".join(f"{k} {v}" for k, v in sorted(counts.results.items())) or "none"
    click.echo(f"{output}: {counts.pairs} pairs, results: {per_algo}, odometry "
               f"{counts.odometry}, detections {counts.detections}, malformed "
               f"{counts.malformed}")


def _pipeline_ended(run_dir: Path) -> Callable[[], bool]:
    """Whether the pipeline of run_dir, once seen running, has ended (its supervisor gone,
    every process of it stopped). One not started yet is waited for."""
    from trapflow.supervisor.setup import supervisor_alive

    seen = False

    def ended() -> bool:
        nonlocal seen
        alive = supervisor_alive(run_dir)
        seen = seen or alive
        return seen and not alive

    return ended


def _status_rig(run_dir: Path, status: Mapping[str, Any]) -> StereoRig | None:
    """The rig in the status of the pipeline running in run_dir (for CameraInfo), None
    when it names none, or None with a warning when it cannot be read."""
    try:
        found = status.get("rig")
        if found:
            return msgspec.convert({k: v for k, v in found.items()
                                    if k in StereoRig.__struct_fields__}, StereoRig)
    except msgspec.ValidationError as exc:
        click.echo(f"warning: no rig from {run_dir} ({exc}); recording without CameraInfo",
                   err=True)
    return None


def lossless_problems(pairs_read: int, stats: Stats, pools: Iterable[str],
                      capture_failures: Mapping[str, int] | None = None,
                      gated: Iterable[str] = ()) -> list[str]:
    """Why a replay was not lossless: pairs capture could not read, pairs that did not
    enter, or a pool that ran and did not end every pair as processed (dropped, failed,
    timed out, lost). A pool in `gated` (replayed with --gate, `gate: motion`) may also end
    a pair as withheld by the motion gate (`gated`): accounted for, by design, not lost;
    none may still be held as the gate's pre-roll."""
    problems = []
    if failed := sum((capture_failures or {}).values()):
        kinds = ", ".join(f"{k} {n}" for k, n in sorted((capture_failures or {}).items()))
        problems.append(f"{failed} pairs failed at capture ({kinds})")
    if stats.pairs_in != pairs_read:
        problems.append(f"read {pairs_read} pairs from the recording, {stats.pairs_in} entered")
    behind_gate = set(gated)
    for name in sorted(pools):
        pool = stats.pools.get(name, PoolStats())
        withheld = pool.gated if name in behind_gate else 0
        if (pool.processed + withheld != pairs_read or pool.errors or pool.timed_out
                or pool.kept):
            gate = (f"gated {pool.gated}, still kept {pool.kept}, " if name in behind_gate
                    else "")
            problems.append(f"pool {name}: processed {pool.processed} of {pairs_read} "
                            f"({gate}dropped {pool.dropped}, failed {pool.errors}, "
                            f"timed out {pool.timed_out}, lost {pool.lost})")
    return problems


def _replay_config(path: Path, config_path: str | None, loop: bool, opts: dict[str, Any],
                   workers: dict[str, int] | None, size: tuple[int, int] | None,
                   gate: bool) -> Config:
    """The config of a replay: the file's, with the replay source and the flags over it;
    without `gate` every pool takes every pair (config.schema.with_gate)."""
    from trapflow import registry
    from trapflow.config import schema as config_mod

    cfg = config_mod.with_gate(config_mod.load(config_path), gate)
    src: dict[str, Any] = {"kind": "replay", "uri": str(path), "loop": loop,
                           "options": {**cfg.source.options, **opts}}
    if size is not None:
        src["width"], src["height"] = size
    cfg = config_mod.with_source(cfg, **src)
    if workers is not None:
        cfg = config_mod.with_workers(cfg, workers, registry.known_names(),
                                      registry.TEST_KIT)
    return cfg


@click.command()
@click.argument("path", type=click.Path(path_type=Path))
@click.option("--rate", type=click.FloatRange(min=0), default=1.0, show_default=True,
              help="Speed relative to the original timing; 0 = as fast as the slowest pool.")
@click.option("--loop", is_flag=True, help="Start over at the end instead of stopping.")
@click.option("--assert-lossless", is_flag=True,
              help="Fail (status 1) unless every pair read was processed by every pool (with "
              "--gate: processed, or withheld by the motion gate and counted gated).")
@click.option("--gate", is_flag=True,
              help="Apply the motion gate as configured (pools with gate: motion get only the "
              "pairs it lets through); default: every pair to every pool.")
@click.option("-c", "--config", "config_path", type=click.Path(dir_okay=False), default=None)
@click.option("--workers", type=WorkersType(),
              help="Pools to run and their sizes, e.g. vo=1,tags=2 (others off).")
@click.option("--size", type=SizeType(), help="Image size, e.g. 752x480.")
@click.option("--duration", type=click.FloatRange(min=0, min_open=True),
              help="Stop after this many seconds.")
@click.option("--option", "options", multiple=True, metavar="KEY=VALUE",
              help="Replay option (left_topic, right_topic, tolerance_s, msg_type, msg_def...).")
@click.option("--run-dir", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="Where results, logs and sockets go (default: runs/<timestamp>).")
def replay(path: Path, rate: float, loop: bool, assert_lossless: bool, gate: bool,
           config_path: str | None, workers: dict[str, int] | None,
           size: tuple[int, int] | None, duration: float | None, options: tuple[str, ...],
           run_dir: Path | None) -> None:
    """Feed a trapflow recording or a ROS 2 bag through the pipeline.

    A recording cut by a crash (FILE.part) is replayed up to its last complete message.
    """
    from trapflow.config.schema import with_source
    from trapflow.recording.recorder import PART_SUFFIX, recover
    from trapflow.sources.replay import ReplaySource
    from trapflow.sources.rig import from_config
    from trapflow.supervisor.run import run

    if assert_lossless and loop:
        raise click.UsageError("--assert-lossless needs a finite replay; drop --loop")
    opts: dict[str, Any] = {"rate": rate}
    for item in options:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise click.BadParameter(f"expected KEY=VALUE, got {item!r}", param_hint="--option")
        opts[key] = value
    with contextlib.ExitStack() as stack:
        try:
            cfg = _replay_config(path, config_path, loop, opts, workers, size, gate)
            if path.name.endswith(PART_SUFFIX) and path.is_file():
                tmp = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="trapflow-")))
                whole = tmp / path.name[: -len(PART_SUFFIX)]
                n = recover(path, whole)
                click.echo(f"replay {path}: an unfinished recording; its {n} complete "
                           "messages are replayed", err=True)
                cfg = with_source(cfg, uri=str(whole))
            # Counting also gives one clear error up front.
            pairs = ReplaySource(cfg.source, from_config(cfg)).count_pairs()
        except TrapflowError as exc:
            raise bad_input(exc) from None
        click.echo(f"replay {path}: {pairs} pairs at rate {rate:g}", err=True)
        try:
            result = run(cfg, run_dir, duration, announce=click.echo)
        except TrapflowError as exc:
            raise failed(exc) from None
    if result.code != 0:
        raise CommandFailed(result.failure or f"the pipeline stopped with status {result.code}",
                            result.code)
    stats = result.stats
    if stats is None:
        if assert_lossless:
            raise failed("--assert-lossless: the pipeline returned no final stats")
        return
    click.echo(f"pairs read {pairs}, delivered {stats.pairs_in}")
    ran = [name for name, pool in cfg.pools.items() if pool.count > 0]
    gated = [name for name in ran if cfg.pools[name].gate == "motion"]
    if gated:
        click.echo("motion gate on: " + ", ".join(
            f"{name} gated {stats.pools.get(name, PoolStats()).gated}" for name in gated))
    if assert_lossless and (problems := lossless_problems(pairs, stats, ran,
                                                          result.capture_failures, gated)):
        raise failed("replay was not lossless: " + "; ".join(problems))


@click.command()
@click.argument("path", type=click.Path(dir_okay=False, path_type=Path))
@click.option("-o", "--output", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="MCAP file to write (default: PATH without .part).")
@force_option()
def recover(path: Path, output: Path | None, force: bool) -> None:
    """Make a recording cut by a crash or power loss (FILE.part) a valid MCAP file.

    Every message up to the last complete one is kept.
    """
    from trapflow.recording.recorder import recover as recover_file
    from trapflow.recording.recorder import recovered_name

    out = output or recovered_name(path)
    check_outputs("recover", [Out(out, "-o"),
                              Out(out.with_name(out.name + ".recovering"), "-o", scratch=True)],
                  [In(path, "PATH")], force)
    try:
        n = recover_file(path, out)
    except TrapflowError as exc:
        raise bad_input(exc) from None
    click.echo(f"{out}: {n} messages recovered from {path}")
