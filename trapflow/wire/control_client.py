"""Client side of the supervisor's control socket: `trapflow status`, `--stop`, and the
runtime changes `trapflow pool` and `trapflow param`."""

from __future__ import annotations

import json
import os
import pwd
from pathlib import Path
from typing import Any

import zmq

from trapflow.config import schema as configmod
from trapflow.errors import StartupError
from trapflow.wire import control_msgs, messages
from trapflow.wire.endpoints import Endpoints
from trapflow.wire.transport import SocketSpec, new_context, open_socket


def request(run_dir: Path, what: str | messages.Msg, timeout_s: float = 3.0,
            cfg: configmod.Config | None = None) -> dict[str, Any]:
    """Send one control request ("status", "stop" or a request message) and return the
    decoded JSON reply."""
    cfg = cfg or configmod.Config()
    if not run_dir.exists():
        raise StartupError(f"no run directory {run_dir}: is a pipeline running there?")
    ep = Endpoints.for_run(cfg.network, run_dir).control
    _check_reachable(run_dir, ep)
    ctx = new_context()
    try:
        sock = open_socket(ctx, SocketSpec(zmq.REQ, ep))
        req = what if isinstance(what, messages.Msg) else \
            control_msgs.StopRequest() if what == "stop" else control_msgs.StatusRequest()
        sock.send(messages.encode(req))
        if not sock.poll(int(timeout_s * 1000), zmq.POLLIN):
            raise StartupError(f"no answer from {ep} within {timeout_s:g} s: "
                               "is a pipeline running in that run directory?")
        reply: dict[str, Any] = json.loads(sock.recv())
        return reply
    finally:
        ctx.destroy(linger=0)


def _check_reachable(run_dir: Path, endpoint: str) -> None:
    """A control socket in a run directory this user may not enter (0700, another user's,
    as a systemd unit's) is refused by the system, which zmq only shows as no answer."""
    if not endpoint.startswith("ipc://"):
        return
    try:
        os.stat(endpoint.removeprefix("ipc://"))
    except PermissionError:
        try:
            owner = pwd.getpwuid(run_dir.stat().st_uid).pw_name
        except (OSError, KeyError):
            owner = "its owner"
        raise StartupError(
            f"cannot reach the pipeline in {run_dir}: permission denied (the run directory "
            f"is private to {owner}); run the command as that user, e.g. `sudo -u {owner} "
            f"trapflow status --run-dir {run_dir}`") from None
    except OSError:
        pass  # no socket (yet): the request says that no pipeline answers


class ControlClient:
    """A control client for a node's loop (the modem's surface commands): one request at a
    time, never blocking; a request the supervisor does not answer within its time is given
    up with an error reply (the REQ socket is then replaced, as REQ allows no second send)."""

    def __init__(self, ctx: zmq.Context[zmq.Socket[bytes]], endpoint: str) -> None:
        self.ctx = ctx
        self.endpoint = endpoint
        self._sock: zmq.Socket[bytes] | None = None
        self.deadline: float | None = None  # set while a request waits for its reply
        self.timeout_s = 0.0

    @property
    def busy(self) -> bool:
        """True while a request waits for its reply."""
        return self.deadline is not None

    def send(self, req: messages.Msg, timeout_s: float, now: float) -> None:
        """Send one request; poll() gives its reply."""
        if self.busy:
            raise RuntimeError("ControlClient.send while a request is waiting")
        if self._sock is None:
            self._sock = open_socket(self.ctx, SocketSpec(zmq.REQ, self.endpoint))
        self._sock.send(messages.encode(req), zmq.NOBLOCK)
        self.deadline, self.timeout_s = now + timeout_s, timeout_s

    def poll(self, now: float) -> dict[str, Any] | None:
        """The reply once it came (or an error once the time is over); None meanwhile."""
        if self.deadline is None or self._sock is None:
            return None
        if self._sock.poll(0, zmq.POLLIN):
            self.deadline = None
            try:
                reply: dict[str, Any] = json.loads(self._sock.recv())
            except ValueError as exc:
                return {"error": f"the supervisor's reply is not JSON: {exc}"}
            return reply
        if now < self.deadline:
            return None
        self.close()
        return {"error": f"the supervisor did not answer within {self.timeout_s:g} s; the "
                         "change may still be made: ask for status"}

    def close(self) -> None:
        """Drop the socket (and any request waiting)."""
        if self._sock is not None:
            self._sock.close(linger=0)
        self._sock = None
        self.deadline = None


def parse_assignment(text: str) -> tuple[str, Any]:
    """`KEY=VALUE` of `trapflow param`: the value read as YAML (0.5, true, text), a scalar."""
    import yaml

    key, sep, raw = text.partition("=")
    if not sep or not key.strip():
        raise ValueError(f"expected KEY=VALUE (e.g. conf_threshold=0.5), got {text!r}")
    try:
        value = yaml.safe_load(raw) if raw.strip() else ""
    except yaml.YAMLError:
        value = raw
    if not isinstance(value, (str, int, float, bool)) and value is not None:
        raise ValueError(f"{key.strip()}: expected a single value (number, true/false, text), "
                         f"got {type(value).__name__} {raw!r}; set lists and maps in the "
                         "config file")
    return key.strip(), value
