"""`trapflow dataset synth OUT`: write a synthetic stereo dataset with ground truth."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click
import yaml

from trapflow.calibration.camera import StereoRig
from trapflow.cli.outputs import Out, check_outputs
from trapflow.errors import ConfigError
from trapflow.synth.dataset import write_synth
from trapflow.synth.options import parse_options

# The default world's seed: its first scene has animals from the second pair on (seed 0's
# first 20 s are an empty scene, so a short default dataset had no annotation at all).
DEFAULT_SEED = 96


class OptionType(click.ParamType[tuple[str, Any]]):
    """KEY=VALUE, the value read as a YAML scalar (0.5, true, 3)."""

    name = "KEY=VALUE"

    def convert(self, value: Any, param: click.Parameter | None,
                ctx: click.Context | None) -> tuple[str, Any]:
        if isinstance(value, tuple):
            return value
        key, sep, raw = str(value).partition("=")
        if not sep or not key.strip():
            self.fail(f"expected KEY=VALUE, got {value!r}", param, ctx)
        try:
            parsed = yaml.safe_load(raw)
        except yaml.YAMLError:
            self.fail(f"{key}: value {raw!r} is not a scalar", param, ctx)
        return key.strip(), parsed


@click.group("dataset")
def dataset() -> None:
    """Make datasets."""


@dataset.command("synth")
@click.argument("out", type=click.Path(file_okay=False, path_type=Path))
@click.option("--frames", type=click.IntRange(min=1), required=True, help="Pairs to render.")
@click.option("--seed", type=click.IntRange(min=0), default=DEFAULT_SEED, show_default=True,
              help="Seed of the world.")
@click.option("--moving", is_flag=True, help="The rig moves along a known trajectory.")
@click.option("--width", type=click.IntRange(16, 8192), default=1280, show_default=True)
@click.option("--height", type=click.IntRange(16, 8192), default=720, show_default=True)
@click.option("--rate", "rate_hz", type=click.FloatRange(0, 240, min_open=True), default=15.0,
              show_default=True, help="Pairs per second (sets the time between pairs).")
@click.option("--baseline", type=click.FloatRange(0, 10, min_open=True), default=0.12,
              show_default=True, help="Stereo baseline in metres.")
@click.option("--hfov", type=click.FloatRange(1, 179, min_open=True, max_open=True),
              default=70.0, show_default=True, help="Horizontal field of view, degrees.")
@click.option("--option", "-o", "options", type=OptionType(), multiple=True,
              help="World option KEY=VALUE (as source.options), repeatable.")
@click.option("--force", "--overwrite", "force", is_flag=True,
              help="Write into an OUT that is not empty: the dataset's own files and folders "
                   "in it are replaced, anything else is left as it is.")
def synth(out: Path, frames: int, seed: int, moving: bool, width: int, height: int,
          rate_hz: float, baseline: float, hfov: float, options: tuple[tuple[str, Any], ...],
          force: bool) -> None:
    """Render a KITTI-style stereo sequence with YOLO labels into OUT, with data.yaml and
    images/ beside labels/ for Ultralytics and the same boxes in coco.json."""
    check_outputs("dataset synth", [Out(out, "OUT", folder=True, force_does=(
        "write into it (the dataset's own files and folders in it are replaced)"))],
        force=force)
    rig = StereoRig.from_fov(width, height, hfov, baseline)
    try:
        opts = parse_options(dict(options), prefix="--option")
        counts = write_synth(out, frames=frames, seed=seed, moving=moving, rig=rig,
                             rate_hz=rate_hz, options=opts, overwrite=force)
    except ConfigError as exc:
        raise click.UsageError(str(exc)) from None
    summary = ", ".join(f"{k}={v}" for k, v in sorted(counts.items()))
    click.echo(f"wrote {frames} pairs to {out} ({summary})")
    if not any(n for k, n in counts.items() if not k.startswith("scene:")):
        click.echo(f"warning: no animal or tag was labelled in these {frames} pairs (seed "
                   f"{seed}): the dataset has no annotation; give more --frames or another "
                   "--seed", err=True)
