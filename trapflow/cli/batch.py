"""The `trapflow process` command: parse, load config, call trapflow.batch.run.process."""

from __future__ import annotations

from pathlib import Path

import click

from trapflow.batch.plan import WHOLE, find_inputs
from trapflow.cli.exit import CommandFailed, bad_input, failed
from trapflow.cli.outputs import In, Out, check_outputs
from trapflow.config import schema as configmod
from trapflow.errors import TrapflowError


class ChunkSizeType(click.ParamType[int]):
    """A number of pairs >= 1, or `whole` for the whole sequence in one chunk."""

    name = "N|whole"

    def convert(self, value: object, param: click.Parameter | None,
                ctx: click.Context | None) -> int:
        if isinstance(value, int):
            return value
        text = str(value).strip().lower()
        if text == "whole":
            return WHOLE
        if text.isdigit() and int(text) >= 1:
            return int(text)
        self.fail(f"expected a number of pairs >= 1 or 'whole', got {value!r}", param, ctx)


class PoolsType(click.ParamType[tuple[str, ...]]):
    """Comma-separated pool names, e.g. mono,stereo,vo,tags."""

    name = "POOL[,POOL...]"

    def convert(self, value: object, param: click.Parameter | None,
                ctx: click.Context | None) -> tuple[str, ...]:
        if isinstance(value, tuple):
            return value
        names = tuple(p.strip() for p in str(value).split(","))
        if not names or not all(n.isidentifier() for n in names) or len(set(names)) != len(names):
            self.fail(f"expected distinct pool names separated by commas, e.g. mono,vo, "
                      f"got {value!r}", param, ctx)
        return names


@click.command()
@click.argument("inputs", nargs=-1, required=True)
@click.option("--workers", "pools", type=PoolsType(), default="mono,stereo,vo,tags",
              show_default=True, help="Pools to run on every pair (names from the config).")
@click.option("--config", "config_path", type=click.Path(dir_okay=False),
              help="YAML config: the same plugins, params and rig settings as `start`.")
@click.option("--out", type=click.Path(file_okay=False, path_type=Path), default=Path("processed"),
              show_default=True, help="Output folder; the same one again resumes a run.")
@click.option("--scheduler", help="Address of an existing dask scheduler (tcp://HOST:8786).")
@click.option("--local", type=click.IntRange(min=1, max=256),
              help="Workers of the LocalCluster (default: one per CPU core).")
@click.option("--chunk", type=click.IntRange(min=1), default=64, show_default=True,
              help="Pairs per chunk of the pools that are not ordered (mono, stereo, tags).")
@click.option("--vo-chunk", type=ChunkSizeType(), default="whole", show_default=True,
              help="Pairs per chunk of an ordered pool (policy ordered: visual odometry), "
              "or 'whole' to keep it sequential.")
@click.option("--vo-overlap", type=click.IntRange(min=0), default=4, show_default=True,
              help="Pairs an ordered pool's chunk starts early to re-initialise on (VO's "
              "drift is reported).")
@click.option("--retries", type=click.IntRange(min=0, max=10), default=2, show_default=True,
              help="Dask retries of a failed chunk before it is reported.")
def process(inputs: tuple[str, ...], pools: tuple[str, ...], config_path: str | None,
            out: Path, scheduler: str | None, local: int | None, chunk: int, vo_chunk: int,
            vo_overlap: int, retries: int) -> None:
    """Re-analyse finite inputs (recordings, bags, image folders, videos, or folder trees of
    them) on dask.distributed, with the live pipeline's plugins, rig and result JSON."""
    from trapflow.batch.run import Options
    from trapflow.batch.run import process as run_process

    if scheduler and local:
        raise click.UsageError("give --scheduler ADDRESS or --local N, not both")
    # The same --out again resumes: what is there is kept and added to, never replaced.
    check_outputs("process", [Out(out, "--out", folder=True, appends=True)],
                  [*(In(Path(p), "INPUT") for p in inputs),
                   *([In(Path(config_path), "--config")] if config_path else [])])
    try:
        cfg = configmod.load(config_path)
        found = find_inputs(inputs)
    except TrapflowError as exc:
        raise bad_input(exc) from None
    opts = Options(pools=pools, chunk=chunk, vo_chunk=vo_chunk, vo_overlap=vo_overlap,
                   retries=retries, local=local or 0, scheduler=scheduler)
    try:
        summary = run_process(cfg, found, out, opts, click.echo,
                              lambda s: click.echo(s, err=True))
    except TrapflowError as exc:
        raise failed(exc) from None
    click.echo((out / "summary.txt").read_text(), nl=False)
    if summary.failures:
        raise CommandFailed(f"{len(summary.failures)} failures (see {out}/*/ledger.json): "
                            + "; ".join(summary.failures)[:800])
