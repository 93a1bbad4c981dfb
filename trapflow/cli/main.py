"""The `trapflow` command line: thin click commands that parse, load config, call one function."""

from __future__ import annotations

from pathlib import Path
from typing import Any, NoReturn

import click

from trapflow import registry
from trapflow.cli.exit import CommandFailed, failed
from trapflow.cli.outputs import Out, check_outputs, force_option
from trapflow.cli.sources import SizeType, SourceSpecType, WorkersType
from trapflow.cli.view_params import ViewAddressType
from trapflow.config import schema as configmod
from trapflow.errors import EXIT_USAGE, TrapflowError
from trapflow.viewer.access import console_address, new_token


def _fail(exc: TrapflowError) -> NoReturn:
    """End the command with the error's one line and the status the policy gives it."""
    raise failed(exc) from None


# click 8.2+ asks for help with an error of its own (a bare `trapflow`): help, not an error.
_HELP: type[Exception] | tuple[()] = getattr(click.exceptions, "NoArgsIsHelpError", ())


def _usage(exc: click.UsageError) -> click.ClickException:
    """click's usage error (4 lines: usage, hint, blank, error) as one line, status 2."""
    if isinstance(exc, _HELP):
        return exc  # a UsageError: click prints the help
    where = exc.ctx.command_path if exc.ctx is not None else "trapflow"
    return CommandFailed(f"{where}: {exc.format_message()} (see '{where} --help')", EXIT_USAGE)


class TrapflowGroup(click.Group):
    """Any trapflow error a command lets through ends it by the exit-code policy, never
    with a traceback (modem and dataset commands included); a usage error is one line too."""

    def make_context(self, info_name: str | None, args: list[str],
                     parent: click.Context | None = None, **extra: Any) -> click.Context:
        try:
            return super().make_context(info_name, args, parent, **extra)
        except click.UsageError as exc:  # an option of `trapflow` itself
            raise _usage(exc) from None

    def invoke(self, ctx: click.Context) -> Any:
        try:
            return super().invoke(ctx)
        except TrapflowError as exc:
            raise failed(exc) from None
        except click.UsageError as exc:  # a command's options or arguments, or no command
            raise _usage(exc) from None


# Every option can come from the environment as TRAPFLOW_<COMMAND>_<OPTION> (a systemd
# unit's Environment=, a container's env), e.g. TRAPFLOW_START_RUN_DIR; a flag given on the
# command line wins. See docs/deploy.md.
ENVVAR_PREFIX = "TRAPFLOW"


@click.group(cls=TrapflowGroup, context_settings={"auto_envvar_prefix": ENVVAR_PREFIX})
@click.version_option(package_name="trapflow")
def main() -> None:
    """trapflow: stereo capture, worker pools over ZeroMQ, compact results.

    Any option may be set in the environment as TRAPFLOW_<COMMAND>_<OPTION>, e.g.
    TRAPFLOW_START_RUN_DIR=/var/lib/trapflow/run."""


@main.command()
@click.option("--config", "config_path", type=click.Path(dir_okay=False),
              help="YAML config (default: built-in defaults, as in configs/default.yaml).")
@click.option("--workers", type=WorkersType(),
              help="Pools to run and their sizes, e.g. mono=2,stereo=1,vo=1 (others off).")
@click.option("--duration", type=click.FloatRange(min=0, min_open=True),
              help="Stop after this many seconds.")
@click.option("--run-dir", type=click.Path(file_okay=False, path_type=Path),
              help="Where results, logs and sockets go (default: runs/<timestamp>).")
@click.option("--rate", type=click.FloatRange(min=0, min_open=True, max=240),
              help="Capture rate in pairs/s.")
@click.option("--size", type=SizeType(), help="Image size, e.g. 1280x720.")
@click.option("--encoding", type=click.Choice(["jpeg", "raw"]), help="Pair payload.")
@click.option("--seed", type=int, help="Seed of the synthetic world.")
@click.option("--moving/--static", default=None, help="Synthetic rig moves or stands.")
@click.option("--source", "source_spec", type=SourceSpecType(),
              help="KIND:ARGS, e.g. video:l.mp4,r.mp4, images:DIR, v4l2:/dev/video0,/dev/video2, "
                   "replay:rec.mcap (default: the synthetic world).")
@click.option("--loop", is_flag=True, default=None, help="Restart a finite source at its end.")
@click.option("--view", type=ViewAddressType(), metavar="[HOST:]PORT",
              help="Serve the live web viewer and /metrics here (host 127.0.0.1 by default).")
@click.option("--metrics-file", type=click.Path(dir_okay=False),
              help="Write Prometheus metrics to this node_exporter textfile (needs --view).")
def start(config_path: str | None, workers: dict[str, int] | None, duration: float | None,
          run_dir: Path | None, rate: float | None, size: tuple[int, int] | None,
          encoding: str | None, seed: int | None, moving: bool | None,
          source_spec: tuple[str, str] | None, loop: bool | None,
          view: tuple[str, int] | None, metrics_file: str | None) -> None:
    """Run the pipeline: capture, broker, worker pools and normalizer (with a `schedule:`,
    only inside its recording windows)."""
    from trapflow.supervisor.windows import run_scheduled as run_pipeline

    try:
        cfg = configmod.load(config_path)
        src = _given(rate_hz=rate, encoding=encoding, seed=seed, moving=moving,
                     loop=loop or None)
        if size is not None:
            src["width"], src["height"] = size
        if source_spec is not None:
            src["kind"], src["uri"] = source_spec
        cfg = configmod.with_source(cfg, **src)
        if workers is not None:
            cfg = configmod.with_workers(cfg, workers, registry.known_names(),
                                        registry.TEST_KIT)
        if metrics_file is not None and view is None and not cfg.viewer.enabled:
            raise click.UsageError("--metrics-file is written by the viewer: add --view PORT")
        cfg = _with_viewer(cfg, view, metrics_file, enabled=view is not None or None)
    except TrapflowError as exc:
        raise CommandFailed(str(exc), EXIT_USAGE) from None
    try:
        result = run_pipeline(cfg, run_dir, duration, announce=click.echo)
    except TrapflowError as exc:
        _fail(exc)
    if result.code != 0:
        raise CommandFailed(result.failure or f"the pipeline stopped with status {result.code}",
                            result.code)


def _given(**values: Any) -> dict[str, Any]:
    """The options that were given on the command line (those not None)."""
    return {k: v for k, v in values.items() if v is not None}


def _with_viewer(cfg: configmod.Config, view: tuple[str, int] | None, metrics_file: str | None,
                 enabled: bool | None = None) -> configmod.Config:
    """The config with the viewer flags applied."""
    changes = _given(enabled=enabled, metrics_file=metrics_file)
    if view is not None:
        changes["host"], changes["port"] = view
    return configmod.with_section(cfg, "viewer", **changes)


@main.command()
@click.option("--run-dir", type=click.Path(file_okay=False, path_type=Path),
              default=Path("runs/latest"), show_default=True)
@click.option("--config", "config_path", type=click.Path(dir_okay=False),
              help="The pipeline's YAML config (its network section finds the sockets).")
@click.option("--listen", type=ViewAddressType(), metavar="[HOST:]PORT",
              help="Where the page and /metrics are served (default: the config's, "
                   "127.0.0.1:8090).")
@click.option("--metrics-file", type=click.Path(dir_okay=False),
              help="Also write Prometheus metrics to this node_exporter textfile.")
def view(run_dir: Path, config_path: str | None, listen: tuple[str, int] | None,
         metrics_file: str | None) -> None:
    """Attach the live web viewer to a running pipeline (Ctrl-C to leave it running)."""
    import asyncio

    from trapflow.viewer.server import serve

    try:
        cfg = _with_viewer(configmod.load(config_path), listen, metrics_file)
    except TrapflowError as exc:
        raise CommandFailed(str(exc), EXIT_USAGE) from None
    if not run_dir.exists():
        raise CommandFailed(f"no run directory {run_dir}: expected the --run-dir of a running "
                            "pipeline (trapflow start prints it)", EXIT_USAGE)
    v = cfg.viewer
    try:
        token = new_token()
        asyncio.run(serve(cfg, run_dir, v.host, v.port, token,
                          ready=lambda url: click.echo(
                              f"viewer: {console_address(url, token)}", err=True)))
    except KeyboardInterrupt:
        pass
    except OSError as exc:
        raise CommandFailed(f"cannot serve on {v.host}:{v.port}: {exc.strerror or exc}; "
                            "choose another with --listen [HOST:]PORT", EXIT_USAGE) from None
    except TrapflowError as exc:  # the viewer's token file
        raise CommandFailed(str(exc), EXIT_USAGE) from None


@main.command()
@click.argument("what", type=click.Choice(["results", "frames", "stats", "truth", "all"]),
                default="all")
@click.option("--count", type=click.IntRange(min=1), help="Stop after N messages.")
@click.option("--save-frames", type=click.Path(file_okay=False, path_type=Path),
              help="Write the JPEG pairs seen into this folder.")
@click.option("--run-dir", type=click.Path(file_okay=False, path_type=Path),
              default=Path("runs/latest"), show_default=True)
@click.option("--endpoint", multiple=True, help="Tap endpoint(s) instead of --run-dir.")
@click.option("--timeout", type=click.FloatRange(min=0, min_open=True),
              help="Give up after this many seconds.")
@force_option("Save frames into a --save-frames folder that is not empty (files of the same "
              "name are replaced).")
def tap(what: str, count: int | None, save_frames: Path | None, run_dir: Path,
        endpoint: tuple[str, ...], timeout: float | None, force: bool) -> None:
    """Attach to a running pipeline and print one line per message."""
    from trapflow.cli.tap import run_tap

    if save_frames is not None:
        check_outputs("tap", [Out(save_frames, "--save-frames", folder=True, force_does=(
            "write into it (files of the same name are replaced)"))], force=force)

    try:
        n = run_tap(what, run_dir, list(endpoint), count, save_frames, timeout,
                    notice=lambda line: click.echo(f"tap: {line}", err=True))
    except TrapflowError as exc:
        _fail(exc)
    where = ", ".join(endpoint) or str(run_dir)
    if timeout is not None and n == 0:
        raise CommandFailed(f"tap received no message from {where} within {timeout:g} s; "
                            "expected a running pipeline there: start one (trapflow start) "
                            "or name its --run-dir")
    if count is not None and n < count:
        raise CommandFailed(f"tap received {n} of the {count} messages asked for (--count) "
                            f"from {where}; the pipeline stopped or --timeout ended first")


@main.command()
@click.option("--run-dir", type=click.Path(file_okay=False, path_type=Path),
              default=Path("runs/latest"), show_default=True)
@click.option("--json", "as_json", is_flag=True, help="Print the raw JSON.")
@click.option("--stop", is_flag=True, help="Ask the pipeline to stop.")
@click.option("--timeout", type=click.FloatRange(min=0, min_open=True), default=3.0,
              show_default=True)
def status(run_dir: Path, as_json: bool, stop: bool, timeout: float) -> None:
    """Show the running pipeline's nodes, lifecycle states, counters and the latest
    interval's counts (visits, MaxN per label)."""
    from trapflow.cli.status_text import format_status
    from trapflow.wire.control_client import request

    try:
        reply = request(run_dir, "stop" if stop else "status", timeout)
    except TrapflowError as exc:
        _fail(exc)
    click.echo(format_status(reply, as_json))


def _control(run_dir: Path, req: Any, timeout: float, as_json: bool) -> None:
    """Send one runtime change; print what changed, or end with why it was refused."""
    import json

    from trapflow.wire.control_client import request

    try:
        reply = request(run_dir, req, timeout)
    except TrapflowError as exc:
        _fail(exc)
    if "error" in reply:
        raise CommandFailed(reply["error"])
    click.echo(json.dumps(reply, indent=2) if as_json else
               f"{reply['changed']}: {reply['change']}")


_RUN_DIR = click.option("--run-dir", type=click.Path(file_okay=False, path_type=Path),
                        default=Path("runs/latest"), show_default=True,
                        help="The running pipeline's run directory.")
_TIMEOUT = click.option("--timeout", type=click.FloatRange(min=0, min_open=True), default=3.0,
                        show_default=True, help="Seconds to wait for the supervisor.")
_JSON = click.option("--json", "as_json", is_flag=True, help="Print the raw JSON reply.")


@main.command()
@click.argument("name")
@click.option("--count", type=click.IntRange(1, 64), help="Run this many workers.")
@click.option("--policy", help="New queueing policy, e.g. latest, fifo:8, ordered:4.")
@click.option("--deactivate", is_flag=True,
              help="Stop giving the pool pairs (counted as dropped while inactive); its "
                   "workers keep their models loaded.")
@click.option("--activate", is_flag=True, help="Give it pairs again.")
@_RUN_DIR
@_TIMEOUT
@_JSON
def pool(name: str, count: int | None, policy: str | None, deactivate: bool, activate: bool,
         run_dir: Path, timeout: float, as_json: bool) -> None:
    """Change a running pool: its worker count, policy, or lifecycle (one change)."""
    from trapflow.wire import control_msgs

    given = [f for f, v in (("--count", count is not None), ("--policy", policy is not None),
                            ("--activate", activate), ("--deactivate", deactivate)) if v]
    active = True if activate else False if deactivate else None
    if len(given) != 1:
        raise click.UsageError(f"expected exactly one of --count, --policy, --activate, "
                               f"--deactivate; got {', '.join(given) or 'none'}")
    # Bounds (name, count) are the control decoder's, checked by the supervisor.
    _control(run_dir, control_msgs.PoolRequest(pool=name, count=count, policy=policy,
                                           active=active), timeout, as_json)


@main.command()
@click.argument("pool_name", metavar="POOL")
@click.argument("assignment", metavar="KEY=VALUE")
@_RUN_DIR
@_TIMEOUT
@_JSON
def param(pool_name: str, assignment: str, run_dir: Path, timeout: float,
          as_json: bool) -> None:
    """Set one plugin parameter of a running pool; its workers restart with it."""
    from trapflow.wire import control_msgs
    from trapflow.wire.control_client import parse_assignment

    try:
        key, value = parse_assignment(assignment)
    except ValueError as exc:
        raise click.UsageError(str(exc)) from None
    _control(run_dir, control_msgs.ParamRequest(pool=pool_name, key=key, value=value), timeout,
             as_json)


@main.command()
@click.argument("level_name", metavar="NAME|auto")
@_RUN_DIR
@_TIMEOUT
@_JSON
def level(level_name: str, run_dir: Path, timeout: float, as_json: bool) -> None:
    """Force the degradation ladder to a level (held until `auto`), or `auto`: the triggers
    decide again."""
    import json

    from trapflow.wire import control_msgs
    from trapflow.wire.control_client import request

    try:
        reply = request(run_dir, control_msgs.LevelRequest(level=level_name), timeout)
    except TrapflowError as exc:
        _fail(exc)
    if "error" in reply:
        raise CommandFailed(reply["error"])
    how = "auto" if reply["auto"] else "forced"
    click.echo(json.dumps(reply, indent=2) if as_json else
               f"level {reply['level']} ({how}): {reply['reason']}")


def _add_commands() -> None:
    from trapflow.cli import dataset as cli_dataset
    from trapflow.cli import export as cli_export
    from trapflow.cli import measure as cli_measure
    from trapflow.cli import modem as cli_modem
    from trapflow.cli import observe as cli_observe
    from trapflow.cli import plan as cli_plan
    from trapflow.cli import remote as cli_remote
    from trapflow.cli import sources as cli_sources
    from trapflow.cli.batch import process

    for cmd in (*cli_modem.COMMANDS, process, cli_sources.calibrate, cli_sources.record,
                cli_sources.replay, cli_sources.recover, cli_dataset.dataset,
                *cli_export.COMMANDS, *cli_remote.COMMANDS, *cli_observe.COMMANDS,
                *cli_measure.COMMANDS, *cli_plan.COMMANDS):
        main.add_command(cmd)


def flag_envvars(group: click.Group, prefix: str = ENVVAR_PREFIX) -> None:
    """Name every option's variable after its flag (TRAPFLOW_START_CONFIG for --config),
    as click's auto_envvar_prefix does for all options whose parameter has the flag's name;
    the others (--config stored as config_path) would otherwise read TRAPFLOW_START_CONFIG_PATH."""
    for name, cmd in group.commands.items():
        sub = f"{prefix}_{name.upper().replace('-', '_')}"
        if isinstance(cmd, click.Group):
            flag_envvars(cmd, sub)
            continue
        for p in cmd.params:
            longs = [o for o in p.opts if o.startswith("--")]
            if isinstance(p, click.Option) and longs and not p.envvar:
                p.envvar = f"{sub}_{longs[0][2:].upper().replace('-', '_')}"


_add_commands()
flag_envvars(main)

if __name__ == "__main__":
    main()
