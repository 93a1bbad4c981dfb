"""`trapflow worker` (a pool's workers on another host) and `trapflow keys` (CURVE keys)."""

from __future__ import annotations

import ipaddress
import socket
import sys
from pathlib import Path
from typing import Any

import click

from trapflow.cli.exit import bad_input
from trapflow.errors import TrapflowError


class TcpEndpointType(click.ParamType[str]):
    """tcp://HOST:PORT."""

    name = "tcp://HOST:PORT"

    def convert(self, value: Any, param: click.Parameter | None,
                ctx: click.Context | None) -> str:
        text = str(value)
        scheme, sep, rest = text.partition("://")
        host, colon, port = rest.rpartition(":")
        if scheme != "tcp" or not sep or not colon or not host or not port.isdigit() or not (
                0 < int(port) < 65536):
            self.fail(f"expected tcp://HOST:PORT, got {text!r}", param, ctx)
        return text


def _loopback(endpoint: str) -> bool:
    host = endpoint.partition("://")[2].rpartition(":")[0].strip("[]")
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return host == "localhost"


@click.command()
@click.option("--connect", "endpoint", required=True, type=TcpEndpointType(),
              help="The pipeline's network.remote.bind, e.g. tcp://192.168.1.10:5560.")
@click.option("--pool", required=True, help="The pool to join (remote: true in its config).")
@click.option("--count", type=click.IntRange(1, 64), default=1, show_default=True,
              help="Worker processes on this host.")
@click.option("--keys", type=click.Path(file_okay=False, path_type=Path),
              help="Folder with this host's client.key_secret and the pipeline's server.key "
                   "(CURVE); needed for any host but loopback.")
@click.option("--name", "host_name", help="This host's name in status (default: hostname).")
@click.option("--run-dir", type=click.Path(file_okay=False, path_type=Path),
              help="Where debug output of `save: true` goes (default: a temporary folder).")
@click.option("--timeout", "join_timeout", type=click.FloatRange(min=0, min_open=True),
              default=10.0, show_default=True,
              help="Give up when the pipeline has not answered within this many seconds.")
def worker(endpoint: str, pool: str, count: int, keys: Path | None, host_name: str | None,
           run_dir: Path | None, join_timeout: float) -> None:
    """Join a running pipeline's pool from this host: COUNT workers, restarted if they die."""
    import logging

    from trapflow.pools.remote_worker import run

    if keys is None and not _loopback(endpoint):
        raise bad_input(f"--connect {endpoint}: expected --keys DIR for a host beyond loopback "
                        f"(CURVE); make them with `trapflow keys generate DIR`")
    if keys is not None and not keys.is_dir():
        raise bad_input(f"--keys: expected a folder with client.key_secret and server.key, "
                        f"got {keys} (no such folder)")
    host = (host_name or socket.gethostname())[:64]
    logging.basicConfig(level=logging.INFO, stream=sys.stderr,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        sys.exit(run(endpoint, pool, count, keys, host, run_dir, join_timeout,
                     announce=click.echo))
    except TrapflowError as exc:
        raise bad_input(exc) from None


@click.group()
def keys() -> None:
    """CURVE keys for a pipeline and its remote workers."""


@keys.command()
@click.argument("folder", type=click.Path(file_okay=False, path_type=Path))
@click.option("--name", default="client", show_default=True,
              help="File name: `server` for a pipeline, `client` for a remote worker.")
def generate(folder: Path, name: str) -> None:
    """Write NAME.key (public, to share) and NAME.key_secret (0600) into FOLDER."""
    from trapflow.wire.keys import generate as make

    try:
        public, secret = make(folder, name)
    except TrapflowError as exc:
        raise bad_input(exc) from None
    click.echo(f"public key {public}")
    click.echo(f"secret key {secret} (keep it on this host)")


COMMANDS = (worker, keys)
