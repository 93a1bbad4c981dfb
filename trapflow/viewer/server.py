"""The viewer's web server (aiohttp): the page, its JSON state, the shown pair, /metrics.
Every request passes the Host allowlist and the token check first, on any bind
(trapflow.viewer.access decides).

One asyncio loop in one process: a pump task drains the taps every PUMP_S and asks the
supervisor for status every STATUS_S; requests only read the state. The page polls
/api/state and fetches a pair only when the shown one changed, so a slow browser simply
sees fewer pairs (the server keeps the latest, never a queue). Images come from the
broker's previews, asked for only while a page is open (a request for the state or a pair
in the last PAGE_OPEN_S): with no page open the pipeline encodes no image for the viewer.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Awaitable, Callable
from importlib import resources
from pathlib import Path

from aiohttp import web

from trapflow.config.schema import Config
from trapflow.errors import ProtocolError, unreachable
from trapflow.viewer import metrics
from trapflow.viewer.access import (
    COOKIE,
    Allow,
    Deny,
    SetCookie,
    bearer_of,
    make_access,
    public_address,
)
from trapflow.viewer.state import ViewState
from trapflow.viewer.taps import PipelineTaps
from trapflow.wire import control_msgs, messages

log = logging.getLogger(__name__)

PUMP_S = 0.05  # tap drain period while a page is open: 20 wake-ups a second
# With no page open: fewer wake-ups and status less often (node states for /metrics).
# Measured on the default pipeline (benchmarks/viewer.py): the idle viewer used 0.67 %
# of a core at 0.05 s, 0.50 % at 0.1 s, 0.37 % at 0.25 s. A result's latency in /metrics
# is taken when its line is drained, so with no page open it reads up to this much late.
PUMP_IDLE_S = 0.2
STATUS_S = 1.0
STATUS_IDLE_S = 5.0
# The page polls twice a second (a background tab of Chromium once a second): a page that
# asked nothing for this long is closed, and previews are no longer asked for.
PAGE_OPEN_S = 3.0
EVENTS_S = 2.0
CONTROL_WAIT_S = 10.0  # a queued change waits for the status request out, then its own
# A connection with no complete request this long is closed (aiohttp's keep-alive timer runs
# from the connection's start), and a request is answered within REQUEST_S or gets 408:
# 400 clients that sent half a request were held for 60 s and more (issue 26 item 10).
IDLE_S = 10.0
REQUEST_S = CONTROL_WAIT_S + 5.0
STATIC = ("index.html", "viewer.js", "viewer.css")
_TYPES = {".html": "text/html", ".js": "text/javascript", ".css": "text/css"}
# A POST that changes the pipeline must carry this header: a page of another site cannot
# set it on a cross-site form post, so a link elsewhere cannot stop the trap.
CONTROL_HEADER = "X-Trapflow-Control"
Handler = Callable[[web.Request], Awaitable[web.StreamResponse]]


class Viewer:
    """The web application over one pipeline's taps."""

    def __init__(self, cfg: Config, run_dir: Path, token: str) -> None:
        self.cfg = cfg
        self.run_dir = run_dir
        self.state = ViewState(cfg.viewer.frame_hz, cfg.observe.interval_s)
        self.taps = PipelineTaps(cfg, run_dir, self.state)
        self.registry = metrics.registry_for(self.state, run_dir)
        mf = cfg.viewer.metrics_file
        self.metrics_file = Path(mf) if mf else None
        self._page_seen = -PAGE_OPEN_S  # monotonic time of the page's last request
        v = cfg.viewer
        self.access = make_access(v.host, v.allowed_hosts, v.token_file, token)
        self.app = web.Application(middlewares=[self._guard])
        self.app.add_routes([
            web.get("/", self._static), web.get("/static/{name}", self._static),
            web.get("/api/state", self._api_state),
            web.get("/frame/{seq}/{side}.jpg", self._frame),
            web.get("/events/{rel:.+}", self._event_image),
            web.get("/metrics", self._metrics),
            web.post("/api/stop", self._stop),
            web.post("/api/pool", self._pool),
        ])

    # --- the loop -----------------------------------------------------------------------

    async def pump(self, beat: Callable[[], None] | None = None,
                   stopping: Callable[[], bool] = lambda: False) -> None:
        """Drain taps, poll status, scan events, write the metrics file, until stopping."""
        next_status = next_events = next_file = 0.0
        while not stopping():
            now = time.monotonic()
            page = now - self._page_seen < PAGE_OPEN_S
            if page and not self.taps.previews:  # a page opened: fresh status at once
                next_status = now
            self.taps.want_previews(page)
            self.taps.drain(now)
            self.state.tick(now)
            if now >= next_status:
                self.taps.poll_status(now)
                next_status = now + (PUMP_S if self.taps.busy() else
                                     STATUS_S if page else STATUS_IDLE_S)
            if now >= next_events:
                self.taps.scan_events()
                next_events = now + EVENTS_S
            if self.metrics_file is not None and now >= next_file:
                metrics.write_textfile(self.registry, self.metrics_file)
                next_file = now + self.cfg.viewer.metrics_interval_s
            if beat is not None:
                beat()
            await asyncio.sleep(PUMP_S if page or self.taps.busy() else PUMP_IDLE_S)

    async def start(self, host: str, port: int) -> web.AppRunner:
        """Bind the HTTP server; OSError if the address is taken."""
        runner = web.AppRunner(self.app, access_log=None, handle_signals=False,
                               keepalive_timeout=IDLE_S)
        await runner.setup()
        await web.TCPSite(runner, host, port).start()
        log.info("viewer on http://%s:%d/ for %s", host, port, self.run_dir)
        return runner

    def url(self, host: str, port: int) -> str:
        """The page's address and where its token is, never the token: it rides on the
        node's state into the log and `trapflow status` (access.console_address adds the
        token for the console)."""
        return public_address(f"http://{host}:{port}/", self.cfg.viewer.token_file)

    def close(self) -> None:
        self.taps.close()

    # --- handlers -----------------------------------------------------------------------

    @web.middleware
    async def _guard(self, request: web.Request, handler: Handler) -> web.StreamResponse:
        """Host allowlist and token before any handler, reads and writes alike."""
        d = self.access.decide(request.headers.get("Host"), request.path,
                               bearer_of(request.headers.get("Authorization")),
                               request.cookies.get(COOKIE), request.query.get("token"))
        if isinstance(d, Allow):
            try:
                return await asyncio.wait_for(handler(request), REQUEST_S)
            except TimeoutError:  # a body sent slowly, or never: the client, not the viewer
                return web.Response(status=408, text=f"request not complete within "
                                    f"{REQUEST_S:g} s\n", headers={"Connection": "close"})
        if isinstance(d, SetCookie):
            resp = web.Response(status=303, headers={"Location": d.location,
                                                     "Cache-Control": "no-store"})
            resp.set_cookie(COOKIE, self.access.token, httponly=True, samesite="Strict",
                            path="/")
            return resp
        if isinstance(d, Deny):
            return web.Response(status=d.status, text=d.reason + "\n",
                                headers={"Cache-Control": "no-store"})
        unreachable(d)

    async def _static(self, request: web.Request) -> web.Response:
        name = request.match_info.get("name", "index.html")
        if name not in STATIC:
            raise web.HTTPNotFound(text=f"no such file {name!r}; expected one of {STATIC}")
        body = resources.files("trapflow.viewer").joinpath("static").joinpath(name).read_bytes()
        return web.Response(body=body, content_type=_TYPES[Path(name).suffix],
                            headers={"Cache-Control": "no-cache"})

    async def _api_state(self, _request: web.Request) -> web.Response:
        self._page_seen = now = time.monotonic()
        snap = self.state.snapshot(now)
        snap["run_dir"] = str(self.run_dir)
        return web.json_response(snap, headers={"Cache-Control": "no-store"})

    async def _frame(self, request: web.Request) -> web.Response:
        side = request.match_info["side"]
        if side not in ("left", "right"):
            raise web.HTTPNotFound(text=f"expected /frame/SEQ/left.jpg or right.jpg, got {side}")
        self._page_seen = time.monotonic()
        shown = self.state.shown
        if shown is None:
            raise web.HTTPNotFound(text="no pair received from the tap yet")
        # The shown pair, whichever seq was asked: the page reads the seq from the header.
        return web.Response(body=shown.left if side == "left" else shown.right,
                            content_type="image/jpeg",
                            headers={"X-Seq": str(shown.seq), "Cache-Control": "no-store"})

    async def _event_image(self, request: web.Request) -> web.FileResponse:
        path = self.taps.event_file(request.match_info["rel"])
        if path is None:
            raise web.HTTPNotFound(text="expected an event image under the run's events folder")
        return web.FileResponse(path)

    async def _metrics(self, _request: web.Request) -> web.Response:
        body = metrics.exposition(self.registry)
        return web.Response(body=body, headers={
            "Content-Type": "text/plain; version=0.0.4; charset=utf-8"})

    def _check_control(self, request: web.Request, what: str) -> None:
        if request.headers.get(CONTROL_HEADER) != what:
            raise web.HTTPForbidden(text=f"expected header {CONTROL_HEADER}: {what} "
                                         "(sent by the viewer's own page)")

    async def _stop(self, request: web.Request) -> web.Response:
        self._check_control(request, "stop")
        self.taps.request_stop()
        log.warning("stop requested from the viewer")
        return web.json_response({"stopping": True})

    async def _pool(self, request: web.Request) -> web.Response:
        """A runtime change of one pool (count, policy, activate/deactivate), as `trapflow
        pool` makes it: 200 with the supervisor's reply, 409 when it refused the change."""
        self._check_control(request, "pool")
        try:
            req = control_msgs.decode_pool_change(await request.read())
        except ProtocolError as exc:
            raise web.HTTPBadRequest(text=str(exc)) from None
        log.info("viewer: pool change requested: %s", messages.to_builtins(req))
        try:
            reply = await asyncio.wait_for(self.taps.request(req), CONTROL_WAIT_S)
        except asyncio.TimeoutError:
            reply = {"error": f"no answer from the supervisor within {CONTROL_WAIT_S:g} s"}
        return web.json_response(reply, status=409 if "error" in reply else 200)


async def serve(cfg: Config, run_dir: Path, host: str, port: int, token: str,
                ready: Callable[[str], None] | None = None,
                beat: Callable[[], None] | None = None,
                stopping: Callable[[], bool] = lambda: False) -> None:
    """Run the viewer until stopping() is true (or the task is cancelled)."""
    viewer = Viewer(cfg, run_dir, token)
    runner = None
    try:
        runner = await viewer.start(host, port)
        if ready is not None:
            ready(viewer.url(host, port))
        await viewer.pump(beat, stopping)
    finally:
        if runner is not None:
            await runner.cleanup()
        viewer.close()
