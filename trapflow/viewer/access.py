"""Who may use the viewer, pure (no sockets): the Host allowlist every request passes, and
the token every request needs, loopback included. The server (trapflow.viewer.server) turns
the decision of `Access.decide` into a response.

Why both: a page of any site the operator opens can rebind its own name to the viewer's
address (DNS rebinding) and then read and drive the viewer as same-origin; it cannot make
the browser send a Host other than its own name, so a Host allowlist shuts it out. Another
user of this machine, or a machine on the network, needs no browser trick at all, so every
bind asks for a token (given once as `?token=` on the page, then kept in an HttpOnly
SameSite=Strict cookie, or sent as `Authorization: Bearer TOKEN` by scripts and Prometheus):
on loopback another local user read live frames, switched a pool off and stopped the
pipeline (issue 36 item 3).

Where the token is: the operator's `viewer.token_file`, or the environment's TOKEN_ENV, or
one made by the process that prints it (the supervisor of `trapflow start --view`, or
`trapflow view`), held in memory only and handed to a viewer node in its spawn spec. The
page's address with `?token=` is printed once, on the console of the user who started the
viewer; no file of the run directory, no log line, no `trapflow status` and no /api/state
carries the token (issue 36 items 3 and 4).
"""

from __future__ import annotations

import hmac
import ipaddress
import os
import secrets
import socket
import stat
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

from trapflow.errors import ConfigError

LOOPBACK_NAMES = ("127.0.0.1", "localhost", "::1")
WILDCARDS = ("0.0.0.0", "::", "")
COOKIE = "trapflow_token"
MIN_TOKEN_CHARS = 16
# An operator's (or a test harness's) own token: readable by the same user only, through
# /proc/PID/environ, as a token file of mode 600 is.
TOKEN_ENV = "TRAPFLOW_VIEWER_TOKEN"
_ON_CONSOLE = " (token: printed on the console that started the viewer)"
_IN_FILE = " (token: the contents of "


def is_loopback(host: str) -> bool:
    """Whether a bind address (or Host name) is this machine's loopback only."""
    if host.lower() in LOOPBACK_NAMES:
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def _is_ip(name: str) -> bool:
    try:
        ipaddress.ip_address(name)
    except ValueError:
        return False
    return True


def host_name(header: str) -> str:
    """The name of a Host header, without port, brackets or trailing dot, lower case."""
    h = header.strip().lower()
    if h.startswith("["):  # [v6]:port
        h = h[1:h.find("]")] if "]" in h else h[1:]
    elif h.count(":") == 1:
        h = h.split(":")[0]
    return h.rstrip(".")


def allowed_hosts(bind: str, configured: Iterable[str]) -> frozenset[str]:
    """The Host names accepted for a bind address: the loopback names and the configured
    ones, and off loopback also the bind address and this machine's name."""
    names = set(LOOPBACK_NAMES) | {host_name(n) for n in configured}
    if not is_loopback(bind):
        if bind not in WILDCARDS:
            names.add(host_name(bind))
        own = socket.gethostname().lower()
        names |= {own, f"{own}.local"}
    return frozenset(n for n in names if n)


def load_token(path: str | Path) -> str:
    """The token from its file: readable by its owner only, at least 16 characters."""
    path = Path(path)
    try:
        st = os.stat(path)
        token = path.read_text().strip()
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"viewer token file {path}: expected a readable text file, got "
                          f"{exc}") from None
    if st.st_mode & 0o077:
        raise ConfigError(f"viewer token file {path} is readable by group or others (mode "
                          f"{stat.S_IMODE(st.st_mode):03o}): expected mode 600")
    if len(token) < MIN_TOKEN_CHARS or not token.isprintable() or " " in token:
        raise ConfigError(f"viewer token file {path}: expected at least {MIN_TOKEN_CHARS} "
                          f"printable characters without spaces, got {len(token)}")
    return token


@dataclass(frozen=True)
class Allow:
    """Serve the request."""


@dataclass(frozen=True)
class SetCookie:
    """The page was loaded with the right `?token=`: keep it in a cookie and go to `location`
    (the address without the token, so it leaves the address bar and the history)."""

    location: str


@dataclass(frozen=True)
class Deny:
    """Refuse with this status and a short reason."""

    status: int
    reason: str


Decision = Allow | SetCookie | Deny


@dataclass(frozen=True)
class Access:
    """The rules of one viewer: which Host names, which token (never empty)."""

    hosts: frozenset[str]
    any_ip: bool  # off loopback: an IP literal is allowed (a rebinding page sends its name)
    token: str

    def decide(self, host: str | None, path: str, bearer: str | None, cookie: str | None,
               query_token: str | None) -> Decision:
        """What to do with one request: Host first (reads and writes alike), then the token."""
        name = host_name(host or "")
        if not name:
            return Deny(403, "expected a Host header")
        if name not in self.hosts and not (self.any_ip and _is_ip(name)):
            return Deny(403, f"Host {name[:64]!r} is not one of the viewer's names "
                             "(viewer.allowed_hosts)")
        for given in (bearer, cookie):
            if given is not None and hmac.compare_digest(given.encode(), self.token.encode()):
                return Allow()
        if (path == "/" and query_token is not None
                and hmac.compare_digest(query_token.encode(), self.token.encode())):
            return SetCookie("/")
        return Deny(401, "expected the viewer's token: open the address printed on the "
                         "console of the user who started it (?token=), or send "
                         "Authorization: Bearer TOKEN")


def new_token() -> str:
    """The token of a viewer started now: the environment's TOKEN_ENV when set (checked like
    a token file's contents), else a fresh random one."""
    given = os.environ.get(TOKEN_ENV, "").strip()
    if not given:
        return secrets.token_urlsafe(24)
    if len(given) < MIN_TOKEN_CHARS or not given.isprintable() or " " in given:
        raise ConfigError(f"{TOKEN_ENV}: expected at least {MIN_TOKEN_CHARS} printable "
                          f"characters without spaces, got {len(given)}")
    return given


def make_access(bind: str, configured: Iterable[str], token_file: str, token: str) -> Access:
    """The rules for a bind address, loopback or not: the token of the configured token
    file when there is one, else `token` (new_token's, made by the process that prints it)."""
    hosts = allowed_hosts(bind, configured)
    any_ip = not is_loopback(bind)
    if token_file:
        return Access(hosts, any_ip, load_token(token_file))
    if len(token) < MIN_TOKEN_CHARS:
        raise ConfigError("viewer: expected a token of at least "
                          f"{MIN_TOKEN_CHARS} characters (new_token) or viewer.token_file")
    return Access(hosts, any_ip, token)


def public_address(base: str, token_file: str) -> str:
    """The page's address as the node's state, the log and `trapflow status` carry it: where
    the token is, never the token."""
    return f"{base}{_IN_FILE}{token_file})" if token_file else f"{base}{_ON_CONSOLE}"


def console_address(public: str, token: str) -> str:
    """The page's address for the console of the user who started the viewer: with
    `?token=` when the token is the one made for it; an operator's token file is named, not
    printed. Unchanged when it is not a public_address."""
    if public.endswith(_ON_CONSOLE) and token:
        return f"{public[: -len(_ON_CONSOLE)]}?token={token}"
    return public


def bearer_of(authorization: str | None) -> str | None:
    """The token of an `Authorization: Bearer TOKEN` header, if that is what it is."""
    if not authorization:
        return None
    scheme, _, value = authorization.partition(" ")
    return value.strip() if scheme.lower() == "bearer" and value.strip() else None
