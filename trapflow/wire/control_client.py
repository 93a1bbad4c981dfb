"""Client side of the supervisor's control socket: `trapflow status`, `--stop`, and the
runtime changes `trapflow pool` and `trapflow param`.

The human status renders the run ledger's own model (trapflow.supervisor.ledger), as the status
line and ledger.json do."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import zmq

from trapflow.config import schema as configmod
from trapflow.errors import StartupError
from trapflow.supervisor import ledger as run_ledger
from trapflow.wire import messages
from trapflow.wire.transport import Endpoints, SocketSpec, new_context, open_socket

# The pool table's columns and their units: counts are pairs since the run started (over
# broker restarts), workers are processes, rate is results per second lately.
POOL_UNITS = {"workers": "procs", "received": "pairs", "processed": "pairs",
              "dropped": "pairs", "inactive": "pairs", "throttled": "pairs", "stale": "pairs",
              "in_flight": "pairs",
              "pending": "pairs",
              "errors": "pairs",
              "timed_out": "pairs", "lost": "pairs", "rate": "pairs/s"}
# Give-ups and retries `trapflow status` lists (the newest); the JSON has them all.
TIMELINE_SHOWN = 5


def request(run_dir: Path, what: str | messages.Msg, timeout_s: float = 3.0,
            cfg: configmod.Config | None = None) -> dict[str, Any]:
    """Send one control request ("status", "stop" or a request message) and return the
    decoded JSON reply."""
    cfg = cfg or configmod.Config()
    if not run_dir.exists():
        raise StartupError(f"no run directory {run_dir}: is a pipeline running there?")
    ep = Endpoints.for_run(cfg.network, run_dir).control
    ctx = new_context()
    try:
        sock = open_socket(ctx, SocketSpec(zmq.REQ, ep))
        req = what if isinstance(what, messages.Msg) else \
            messages.StopRequest() if what == "stop" else messages.StatusRequest()
        sock.send(messages.encode(req))
        if not sock.poll(int(timeout_s * 1000), zmq.POLLIN):
            raise StartupError(f"no answer from {ep} within {timeout_s:g} s: "
                               "is a pipeline running in that run directory?")
        reply: dict[str, Any] = json.loads(sock.recv())
        return reply
    finally:
        ctx.destroy(linger=0)


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


def format_status(reply: dict[str, Any], as_json: bool = False) -> str:
    """A human table of nodes and pool counters, or the JSON itself."""
    if as_json or "nodes" not in reply:
        return json.dumps(reply, indent=2)
    lines = [f"run {reply['run_dir']}  up {reply['uptime_s']} s"]
    r = reply.get("rig")
    if r:
        lines.append(f"rig calib {r['calib']}: {r['width']}x{r['height']}, fx {r['fx']:.1f} "
                     f"fy {r['fy']:.1f} cx {r['cx']:.1f} cy {r['cy']:.1f}, baseline "
                     f"{r['baseline_m']:.3f} m, from {r['origin']}")
    lines.append(f"{'node':<22} {'pid':>7} {'state':<12} {'restarts':>8}  reason")
    lines.append(f"{'':<22} {'':>7} {'(lifecycle)':<12} {'(count)':>8}")
    for n in reply["nodes"]:
        lines.append(f"{n['name']:<22} {n['pid'] or '-':>7} {n['state']:<12} "
                     f"{n['restarts']:>8}  {n['reason']}")
    stats = reply.get("stats")
    if stats:
        lines.append(f"pairs in {stats['pairs_in']} ({stats['rate_in']} pairs/s), "
                     f"malformed {stats['malformed']} messages")
        lines.append(f"{'pool':<10}" + "".join(f"{k:>11}" for k in POOL_UNITS))
        lines.append(f"{'':<10}" + "".join(f"{'(' + u + ')':>11}" for u in POOL_UNITS.values()))
        for name, p in stats["pools"].items():
            lines.append(f"{name:<10}" + "".join(f"{p.get(k, 0):>11}" for k in POOL_UNITS))
        remote = stats.get("remote") or []
        if remote:
            lines.append(f"{'remote worker':<34} {'host':<16} {'pool':<10} {'state':<8} "
                         f"{'processed':>9} {'rate':>7}  reason")
        for r in remote:
            lines.append(f"{r['worker']:<34} {r['host']:<16} {r['pool']:<10} {r['state']:<8} "
                         f"{r.get('processed', 0):>9} {r.get('rate', 0.0):>7}  "
                         f"{r.get('reason', '')}")
    sup = reply.get("supervision")
    if sup:
        lines.append(f"supervision: {sup['gave_up']} give-ups, {sup['retries']} retries, "
                     f"{sup['capped']} capped restarts of essential nodes, "
                     f"{sup.get('control', 0)} runtime changes")
        lad = sup.get("ladder")
        if lad:
            how = "forced" if lad["forced"] else "auto"
            lines.append(f"ladder: level {lad['level']} ({lad['index']} of "
                         f"{len(lad['levels']) - 1}, {how}), {lad['changes']} changes; "
                         f"{lad['reason']}")
        for name, by in sup.get("recycled", {}).items():
            why = ", ".join(f"{k} {n}" for k, n in sorted(by.items()))
            lines.append(f"  pool {name:<10} workers recycled: {why}")
        for name, p in sup.get("pools", {}).items():
            params = ", ".join(f"{k}={v!r}" for k, v in p["params"].items()) or "defaults"
            off = f" (by the {p['off_by']})" if p.get("off_by") else ""
            every = f", at most 1 pair / {p['min_interval_s']:g} s" \
                if p.get("min_interval_s") else ""
            lines.append(f"  pool {name:<10} {p['state']:<9}{off} {p['count']} workers, policy "
                         f"{p['policy']}{every}, params {params}, {p['changes']} changes")
        for e in sup["timeline"][-TIMELINE_SHOWN:]:
            lines.append(f"  {e['t_s']:>8} s  {e['node']:<20} {e['kind']:<8} {e['reason']}")
    if reply.get("ledger"):
        lines.append(run_ledger.totals_text(reply["ledger"]).rstrip("\n"))
    return "\n".join(lines)


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
