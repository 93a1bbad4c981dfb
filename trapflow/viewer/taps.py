"""The viewer's side of a pipeline: its taps, its control socket and its event folders.

Owns a SUB on the broker's tap (stats; previews only while a page is open), a SUB on the
normalizer's (results; each tap takes only subscriptions to its own topics), and a REQ to
the supervisor's control socket. Everything is non-blocking and polled by the server's
loop: PUB sockets drop for a slow subscriber, so the pipeline never waits for the viewer.
The preview subscription is how the viewer tells the broker a page is open: the broker
makes previews (at the viewer's rate) only while somebody subscribes to them.
"""

from __future__ import annotations

import asyncio
import json
import logging
import time
from collections import deque
from pathlib import Path
from typing import Any

import zmq

from trapflow.config.schema import Config
from trapflow.errors import ProtocolError
from trapflow.runtime.ratelog import RateLimitedLog
from trapflow.viewer.state import ViewState
from trapflow.wire import control_msgs, messages, tap_msgs
from trapflow.wire.endpoints import Endpoints
from trapflow.wire.transport import (
    SocketSpec,
    new_context,
    open_socket,
    set_subscribed,
    zmq_readable,
)

log = logging.getLogger(__name__)

# Tap messages taken per drain: a burst never keeps the web server from answering.
MAX_DRAIN = 256
# Previews come at the viewer's rate (at most 15 Hz): a few per drain at most.
TAP_RCVHWM = 16
STATUS_TIMEOUT_S = 2.0
EVENTS_SHOWN = 6


class PipelineTaps:
    """Reads taps and status into a ViewState; sends stop requests."""

    def __init__(self, cfg: Config, run_dir: Path, state: ViewState) -> None:
        self.run_dir = run_dir
        self.state = state
        self.endpoints = Endpoints.for_run(cfg.network, run_dir)
        self.events_dir = run_dir / cfg.events.folder
        self.ctx = new_context()
        self.subs = [
            open_socket(self.ctx, SocketSpec(zmq.SUB, self.endpoints.tap, rcvhwm=TAP_RCVHWM,
                                             subscribe=(tap_msgs.TOPIC_STATS,))),
            open_socket(self.ctx, SocketSpec(zmq.SUB, self.endpoints.results_tap,
                                             subscribe=(tap_msgs.TOPIC_RESULT,))),
        ]
        self.req: zmq.Socket[bytes] | None = None
        self._req_sent = 0.0
        # Control requests from the page, sent one at a time between status requests; the
        # future (if any) gets the supervisor's reply.
        self._queued: deque[tuple[control_msgs.ControlRequest,
                                  asyncio.Future[dict[str, Any]] | None]] = deque()
        self._waiting: asyncio.Future[dict[str, Any]] | None = None
        self._refresh = False  # a change was answered: ask for status at once
        self._control_out = False  # the request out is a queued one (its reply is no status)
        self.ratelog = RateLimitedLog(log)
        self.previews = False

    # --- taps ------------------------------------------------------------------------

    def drain(self, now: float) -> int:
        """Take what the taps hold (at most MAX_DRAIN messages from each) into the state."""
        n = 0
        for sub in self.subs:
            budget = n + MAX_DRAIN
            while n < budget and zmq_readable(sub):  # no exception per empty socket
                frames = sub.recv_multipart(zmq.NOBLOCK, copy=True)
                n += 1
                try:
                    self._feed(frames, now)
                except (ProtocolError, ValueError) as exc:
                    self.state.malformed += 1
                    self.ratelog.warning("tap", "malformed tap message dropped: %s", exc)
        return n

    def want_previews(self, on: bool) -> None:
        """Ask the broker for previews (a page is open) or stop asking (none is)."""
        if on != self.previews:
            set_subscribed(self.subs[0], tap_msgs.TOPIC_PREVIEW, on)
            self.previews = on
            log.debug("viewer: previews %s", "asked for" if on else "no longer asked for")

    def _feed(self, frames: list[bytes], now: float) -> None:
        msg = tap_msgs.decode_tap(frames)
        if isinstance(msg, tap_msgs.TapResult):
            self.state.on_result(msg.kind, msg.fields, time.time())
        elif isinstance(msg, tap_msgs.TapPreview):
            self.state.on_image(msg.header, msg.left, msg.right)
        elif isinstance(msg, tap_msgs.TapStats):
            self.state.on_stats(msg.stats, now)
        else:
            raise ProtocolError(f"tap: expected preview, stats or result, got {msg!r:.60}")

    # --- control ---------------------------------------------------------------------

    def _open_req(self) -> zmq.Socket[bytes]:
        if self.req is None:
            self.req = open_socket(self.ctx, SocketSpec(zmq.REQ, self.endpoints.control))
        return self.req

    def poll_status(self, now: float) -> None:
        """Send the next request when none is out (a queued control request, else status);
        take the reply when it came.

        A REQ that got no answer in time is closed and opened afresh (a REQ cannot send
        twice in a row), and the state says the supervisor does not answer.
        """
        req = self._open_req()
        if self._req_sent:
            if req.poll(0, zmq.POLLIN):
                data = req.recv()
                self._req_sent = 0.0
                try:
                    reply: dict[str, Any] = json.loads(data)
                except ValueError as exc:
                    self._answer({"error": f"reply is not JSON: {exc}"})
                    self.state.on_status(None, f"status reply is not JSON: {exc}")
                    return
                if self._control_out:  # the answer to a change or a stop, not status
                    self._answer(reply)
                    self._refresh = True
                else:
                    self.state.on_status(reply)
            elif now - self._req_sent > STATUS_TIMEOUT_S:
                req.close(linger=0)
                self.req, self._req_sent = None, 0.0
                error = f"no answer from {self.endpoints.control} within {STATUS_TIMEOUT_S:g} s"
                self._answer({"error": error})
                self.state.on_status(None, error)
            return
        what: control_msgs.ControlRequest = control_msgs.StatusRequest()
        self._control_out = bool(self._queued)
        if self._queued:
            what, self._waiting = self._queued.popleft()
        else:
            self._refresh = False
        req.send(messages.encode(what))
        self._req_sent = now

    def busy(self) -> bool:
        """A request is out or waiting to go: poll again soon, not in a second."""
        return bool(self._req_sent or self._queued or self._refresh)

    def _answer(self, reply: dict[str, Any]) -> None:
        fut, self._waiting = self._waiting, None
        if fut is not None and not fut.done():
            fut.set_result(reply)

    def request_stop(self) -> None:
        """The next control request is a stop (sent by poll_status, never blocking)."""
        self._queued.append((control_msgs.StopRequest(), None))

    def request(self, what: control_msgs.PoolRequest | control_msgs.ParamRequest
                ) -> asyncio.Future[dict[str, Any]]:
        """Queue a runtime change; the future gets the supervisor's reply (or an error)."""
        fut: asyncio.Future[dict[str, Any]] = asyncio.get_running_loop().create_future()
        self._queued.append((what, fut))
        return fut

    # --- event folders -----------------------------------------------------------------

    def scan_events(self) -> None:
        """The newest event folders with their first left image as thumbnail."""
        if not self.events_dir.is_dir():
            return
        try:
            folders = sorted((p for p in self.events_dir.iterdir() if p.is_dir()),
                             key=lambda p: p.stat().st_mtime_ns, reverse=True)[:EVENTS_SHOWN]
        except OSError:  # an event deleted by its quota while we looked
            return
        out = []
        for f in folders:
            thumbs = sorted((f / "left").glob("*.jpg"))[:1] if (f / "left").is_dir() else []
            info: dict[str, Any] = {}
            try:
                info = json.loads((f / "event.json").read_text())
            except (OSError, ValueError):
                pass  # still open: no event.json yet
            out.append({"name": f.name, "pairs": info.get("pairs"), "open": not info,
                        "thumb": f"{f.name}/left/{thumbs[0].name}" if thumbs else None})
        self.state.on_events(out)

    def event_file(self, rel: str) -> Path | None:
        """An event image by its relative name, only if it lies inside the events folder."""
        path = (self.events_dir / rel).resolve()
        root = self.events_dir.resolve()
        if root not in path.parents or path.suffix != ".jpg" or not path.is_file():
            return None
        return path

    def close(self) -> None:
        self.ctx.destroy(linger=0)
