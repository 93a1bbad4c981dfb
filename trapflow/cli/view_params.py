"""The viewer's command-line address: `[HOST:]PORT` (no web imports, for a fast CLI)."""

from __future__ import annotations

from typing import Any

import click

DEFAULT_HOST = "127.0.0.1"


def parse_view(text: str, default_host: str = DEFAULT_HOST) -> tuple[str, int]:
    """'[HOST:]PORT' -> (host, port); ValueError saying what was expected."""
    host, sep, port_s = text.rpartition(":")
    bracketed = host.startswith("[") and host.endswith("]")
    host = host[1:-1] if bracketed else host if sep else default_host
    if sep and not host:
        raise ValueError(f"expected [HOST:]PORT with a host before ':', got {text!r}")
    if not all(c.isalnum() or c in ".-" or (bracketed and c == ":") for c in host):
        raise ValueError(f"expected [HOST:]PORT with a host name or address ([::1] for IPv6), "
                         f"got {text!r}")
    if not port_s.isdigit() or not 1 <= int(port_s) <= 65535:
        raise ValueError(f"expected [HOST:]PORT with PORT in 1..65535, got {text!r}")
    return host, int(port_s)


class ViewAddressType(click.ParamType[tuple[str, int]]):
    """`[HOST:]PORT`, host 127.0.0.1 when left out."""

    name = "[HOST:]PORT"

    def convert(self, value: Any, param: click.Parameter | None,
                ctx: click.Context | None) -> tuple[str, int]:
        if isinstance(value, tuple):
            return value
        try:
            return parse_view(str(value))
        except ValueError as exc:
            self.fail(f"{exc}, e.g. 8090 or 127.0.0.1:8090", param, ctx)
