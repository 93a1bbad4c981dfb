"""Click commands for the modem link: `surface` (ship end), `modem-sim` (simulator), `modem-send`.

Thin commands: each parses, builds one library object and runs it until SIGINT/SIGTERM.
`python -m trapflow.cli.modem` runs them without the main `trapflow` group.
"""

from __future__ import annotations

import contextlib
import json
import os
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import IO

import click

from trapflow.cli.outputs import In, Out, check_outputs, force_option
from trapflow.config.modem import DEFAULT_LABELS, ModemConfig, OutboxConfig
from trapflow.runtime.signals import stop_on_signals


def _labels(text: str | None) -> list[str]:
    return list(DEFAULT_LABELS) if not text else [s.strip() for s in text.split(",") if s.strip()]


@contextlib.contextmanager
def _output(path: Path | None) -> Iterator[IO[bytes]]:
    if path is None:
        yield sys.stdout.buffer
    else:
        with open(path, "ab") as out:
            yield out


@click.command("surface")
@click.argument("port")
@click.option(
    "-o",
    "--output",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="JSON lines file to append to (default: standard output).",
)
@click.option(
    "--state",
    "state_path",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="File remembering which messages of which outbox session were written, so a "
    "restarted surface writes a retransmission only once (default: OUTPUT.state beside a "
    "regular output file, or one this run creates; with standard output and no --state the "
    "memory is lost when the command stops).",
)
@click.option("--baudrate", type=click.IntRange(50, 4_000_000), default=9600, show_default=True)
@click.option("--labels", default=None, help="Comma-separated label table (must match the box).")
@click.option(
    "--command",
    "command_text",
    default=None,
    help="Send one signed command to the box, print its reply as JSON and exit (0: done, "
    "1: refused or no reply in --timeout). Results arriving meanwhile are written only with "
    "-o. The commands are listed above.",
)
@click.option(
    "--key",
    "key_path",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="File with the key shared with the box (its modem.command_key), mode 600.",
)
@click.option(
    "--counter",
    "counter_path",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="File keeping the next command counter (default: KEY.counter).",
)
@click.option(
    "--session",
    default=None,
    help="The box's outbox session (8 hex digits; default: the last one heard, from the "
    "state file; the box names its own if this one is wrong).",
)
@click.option(
    "--retry",
    type=click.FloatRange(min=0.1),
    default=8.0,
    show_default=True,
    help="Seconds before the command is sent again (growing by half each time, up to 60).",
)
@click.option(
    "--timeout",
    type=click.FloatRange(min=0.1),
    default=120.0,
    show_default=True,
    help="Seconds to wait for the reply.",
)
def surface(
    port: str,
    output: Path | None,
    state_path: Path | None,
    baudrate: int,
    labels: str | None,
    command_text: str | None,
    key_path: Path | None,
    counter_path: Path | None,
    session: str | None,
    retry: float,
    timeout: float,
) -> None:
    """Receive results from the modem link on PORT, acknowledge them, write JSON lines.

    With --command, send one signed command instead and print the box's reply. Commands:

    \b
    level NAME|auto                  force the degradation ladder to a level, or let it decide
    pool NAME --count N              run N workers in a pool
    pool NAME --activate|--deactivate
    pool NAME --policy POLICY        e.g. latest, fifo:8
    param POOL KEY=VALUE             set one plugin parameter
    status                           a short status now
    health                           a health record now
    """
    from trapflow.modem.surface import SurfaceReceiver

    if state_path is None and output is not None and (
            os.path.isfile(output) or not os.path.lexists(output)):
        # A regular file, or one this run creates (its first run keeps state too: issue 26
        # item 8); not a terminal, pipe or device, which have no place for one beside them.
        state_path = output.with_name(output.name + ".state")
    check_outputs("surface", [Out(p, flag, appends=True) for p, flag in (
        (output, "-o"), (state_path, "--state"), (counter_path, "--counter")) if p is not None],
        [In(key_path, "--key")] if key_path is not None else [])
    if command_text is not None:
        _send_command(
            port,
            output,
            state_path,
            baudrate,
            labels,
            command_text,
            key_path,
            counter_path,
            session,
            retry,
            timeout,
        )
        return
    stop = stop_on_signals()
    with _output(output) as out:
        receiver = SurfaceReceiver(port, out, _labels(labels), baudrate, state_path=state_path,
                                   review_dir=_review_dir(output))
        receiver.run(stop)
    click.echo(json.dumps(receiver.stats()), err=True)


def _review_dir(output: Path | None) -> Path | None:
    """Where the thumbnails of the box's review queue go: `review/` beside the output (none
    on standard output: their lines only)."""
    return None if output is None else output.parent / "review"


def _send_command(
    port: str,
    output: Path | None,
    state_path: Path | None,
    baudrate: int,
    labels: str | None,
    text: str,
    key_path: Path | None,
    counter_path: Path | None,
    session: str | None,
    retry: float,
    timeout: float,
) -> None:
    # Long on purpose: one signed command's exchange with the box from start to end, each
    # step using what the one before opened or read (port, key, counter, session, reply).
    import time

    from trapflow.cli.exit import CommandFailed, bad_input
    from trapflow.errors import TrapflowError
    from trapflow.modem.command import load_key, parse_command_text
    from trapflow.modem.surface import SurfaceReceiver
    from trapflow.modem.surface_command import CommandClient

    try:
        cmd = parse_command_text(text)
    except ValueError as exc:
        raise click.UsageError(f"--command: {exc}") from None
    if key_path is None:
        raise click.UsageError("--command needs --key: the file with the key shared with the box")
    try:
        key = load_key(key_path)
        sid = bytes.fromhex(session) if session else None
    except (TrapflowError, ValueError) as exc:
        raise bad_input(
            str(exc)
            if not isinstance(exc, ValueError)
            else f"--session: expected 8 hex digits, got {session!r}"
        ) from None
    stop = stop_on_signals()
    with contextlib.ExitStack() as stack:
        out = stack.enter_context(open(output, "ab")) if output is not None else None
        receiver = SurfaceReceiver(port, out, _labels(labels), baudrate, state_path=state_path,
                                   review_dir=_review_dir(output))
        if sid is None:  # the last session heard (a wrong one is corrected by the box)
            sid = receiver.current or bytes(4)
        try:
            client = CommandClient(
                key,
                counter_path or key_path.with_name(key_path.name + ".counter"),
                sid,
                cmd,
                retry_s=retry,
            )
        except (TrapflowError, OSError) as exc:
            raise bad_input(exc) from None
        receiver.on_reply = client.on_reply
        deadline = time.monotonic() + timeout
        try:
            while not client.done and not stop.is_set() and time.monotonic() < deadline:
                receiver.step()
                wire = client.due(time.monotonic()) if receiver.port.ensure_open() else None
                if wire is not None:
                    receiver.port.write(wire)
                receiver.port.wait_readable(0.1)
        finally:
            receiver.close()
    click.echo(json.dumps(client.outcome()))
    click.echo(json.dumps({**client.counts, "link": receiver.deframer.stats()}), err=True)
    if not client.ok:
        why = (
            client.outcome().get("error", "no reply")
            if client.done
            else f"no reply within {timeout:g} s"
        )
        raise CommandFailed(f"command {text!r}: {why}")


@click.command("modem-sim")
@click.option("--bit-rate", type=click.FloatRange(min=1), default=300.0, show_default=True)
@click.option(
    "--latency",
    type=click.FloatRange(min=0),
    default=0.5,
    show_default=True,
    help="Seconds a packet travels after its airtime.",
)
@click.option(
    "--loss",
    type=click.FloatRange(0, 1),
    default=0.0,
    show_default=True,
    help="Probability a packet is lost.",
)
@click.option(
    "--corrupt",
    type=click.FloatRange(0, 1),
    default=0.0,
    show_default=True,
    help="Probability a packet has one bit flipped.",
)
@click.option(
    "--noise",
    type=click.FloatRange(0, 1),
    default=0.0,
    show_default=True,
    help="Probability a packet is followed by random bytes.",
)
@click.option("--seed", type=int, default=0, show_default=True)
@click.option(
    "--link-a",
    type=click.Path(path_type=Path),
    default=None,
    help="Symlink to create for the box end.",
)
@click.option(
    "--link-b",
    type=click.Path(path_type=Path),
    default=None,
    help="Symlink to create for the surface end.",
)
@force_option("Replace a --link-a or --link-b path that is there and is not a symlink.")
def modem_sim(
    bit_rate: float,
    latency: float,
    loss: float,
    corrupt: float,
    noise: float,
    seed: int,
    link_a: Path | None,
    link_b: Path | None,
    force: bool,
) -> None:
    """Simulate an acoustic modem between two pseudo-terminals; prints both ends."""
    from trapflow.modem.sim import LinkSimulator

    check_outputs("modem-sim", [Out(p, flag, link=True) for p, flag in (
        (link_a, "--link-a"), (link_b, "--link-b")) if p is not None], force=force)
    stop = stop_on_signals()
    sim = LinkSimulator(bit_rate, latency, loss, corrupt, noise, seed, (link_a, link_b))
    a, b = sim.names
    click.echo(f"box end: {a}")
    click.echo(f"surface end: {b}")
    sys.stdout.flush()
    sim.run(stop)
    click.echo(json.dumps(sim.stats()), err=True)


@click.command("modem-send")
@click.argument("outbox", type=click.Path(dir_okay=False, path_type=Path))
@click.argument("port")
@click.option("--bit-rate", type=click.FloatRange(min=1), default=300.0, show_default=True)
@click.option("--bytes-per-hour", type=click.IntRange(min=0), default=0, show_default=True)
@click.option("--ack-timeout", type=click.FloatRange(min=0.01), default=3.0, show_default=True)
@click.option("--no-aggregate", is_flag=True, help="Never summarise classes that are behind.")
@click.option("--no-ttl", is_flag=True, help="Never expire records.")
def modem_send(
    outbox: Path,
    port: str,
    bit_rate: float,
    bytes_per_hour: int,
    ack_timeout: float,
    no_aggregate: bool,
    no_ttl: bool,
) -> None:
    """Send the records waiting in OUTBOX over the modem link on PORT (outside a pipeline)."""
    from trapflow.modem.sender import ModemSender

    cfg = ModemConfig(
        enabled=True,
        port=port,
        bit_rate=bit_rate,
        bytes_per_hour=bytes_per_hour,
        ack_timeout_s=ack_timeout,
        reopen_interval_s=0.5,
    )
    if no_aggregate:
        cfg.aggregate = []
    if no_ttl:
        cfg.ttl_s = {}
    stop = stop_on_signals()
    sender = ModemSender(outbox, port, cfg, OutboxConfig())
    sender.run(stop)
    click.echo(json.dumps(sender.stats()), err=True)


COMMANDS = (surface, modem_sim, modem_send)


@click.group()
def main() -> None:
    """Modem link commands."""


for _cmd in COMMANDS:
    main.add_command(_cmd)

if __name__ == "__main__":
    main()
