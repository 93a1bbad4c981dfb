"""Benchmark of the live viewer: what it costs the pipeline, with a page open and with none,
against the same pipeline without a viewer, in one run (default pipeline: the synthetic
source at 1280x720, raw pairs in the shared-memory ring, 15 pairs/s asked).

Three windows of the same length: (1) a pipeline without viewer: the broker's CPU per pair
(the baseline); (2) a pipeline with `--view` and no page open; (3) the same pipeline with a
page open: a client polling /api/state twice a second and fetching both images of each new
pair, as viewer.js does (`--client http`, the default), or the page itself in headless
Chromium (`--client chromium`; the browser's own CPU is not counted).

Cost of the viewer in a window = the viewer process's CPU + the broker's CPU beyond the
baseline (the broker's CPU per pair above the baseline's, times the pairs it took), as a
share of one core over the window. CPU = user + system time of the process (psutil).
Usage: python -m benchmarks.viewer [--quick] [--seconds 30 --warmup 15 --client http|chromium
       --out bench-results]   (--quick: 10 s windows after 8 s)
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import psutil

from benchmarks import harness as h

POLL_S = 0.5  # what the page does: /api/state twice a second, both images when they change
BUDGET_OPEN, BUDGET_CLOSED = 0.03, 0.005  # issue 22 item 5: share of one core


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


def _get(url: str) -> bytes:
    with urllib.request.urlopen(url, timeout=5) as r:
        body: bytes = r.read()
        return body


def _node(pipeline: subprocess.Popen[bytes], title: str) -> psutil.Process | None:
    for kid in psutil.Process(pipeline.pid).children(recursive=True):
        try:
            if kid.cmdline()[:1] == [title]:
                return kid
        except psutil.Error:
            continue
    return None


@contextlib.contextmanager
def _pipeline(titles: tuple[str, ...], *args: str) -> Iterator[tuple[list[psutil.Process], Path]]:
    """A default pipeline started with `args` (stopped with SIGINT on leaving), once its
    nodes named by `titles` are up: those nodes' processes and the run directory."""
    run = Path(tempfile.mkdtemp(prefix="tf-bench-")) / "run"
    pipeline = subprocess.Popen(
        [sys.executable, "-m", "trapflow", "start", "--run-dir", str(run), "--size",
         "1280x720", *args],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        deadline = time.monotonic() + 120
        while None in (nodes := [_node(pipeline, t) for t in titles]):
            if time.monotonic() > deadline or pipeline.poll() is not None:
                raise SystemExit(f"the pipeline did not start {', '.join(titles)} within 120 s")
            time.sleep(0.5)
        yield [n for n in nodes if n is not None], run
    finally:
        pipeline.send_signal(signal.SIGINT)
        try:
            pipeline.wait(30)
        except subprocess.TimeoutExpired:
            pipeline.kill()


def _pairs_in(run: Path) -> int:
    """Pairs the broker took so far, from the pipeline's status (its own counter)."""
    out = subprocess.run([sys.executable, "-m", "trapflow", "status", "--json", "--run-dir",
                          str(run), "--timeout", "5"], capture_output=True, text=True,
                         timeout=30, check=True)
    n: int = json.loads(out.stdout)["stats"]["pairs_in"]
    return n


def _window(procs: dict[str, psutil.Process], run: Path, seconds: float,
            during: Callable[[float], dict[str, Any]] | None = None) -> dict[str, Any]:
    """CPU seconds of each process and pairs through the broker over one window; `during`
    runs for the window (a client) and returns what it did."""
    n0 = _pairs_in(run)
    c0 = {k: h.tree_cpu(p.pid) for k, p in procs.items()}
    t0 = time.monotonic()
    extra = during(seconds) if during is not None else _idle(seconds)
    dt = time.monotonic() - t0
    c1 = {k: h.tree_cpu(p.pid) for k, p in procs.items()}
    pairs = _pairs_in(run) - n0
    return {"window_s": round(dt, 1), "pairs": pairs, "rate_hz": round(pairs / dt, 2),
            **{f"{k}_cpu_s": round(c1[k] - c0[k], 3) for k in procs}, **extra}


def _idle(seconds: float) -> dict[str, Any]:
    time.sleep(seconds)
    return {}


def _http_client(base: str) -> Callable[[float], dict[str, Any]]:
    def run(seconds: float) -> dict[str, Any]:
        t0, seq, polls, shown = time.monotonic(), None, 0, 0
        while time.monotonic() - t0 < seconds:
            state = json.loads(_get(f"{base}/api/state"))
            polls += 1
            frame = state.get("frame")
            if frame and frame["seq"] != seq:
                seq = frame["seq"]
                for side in ("left", "right"):
                    _get(f"{base}/frame/{seq}/{side}.jpg")
                shown += 1
            time.sleep(POLL_S)
        return {"client_polls": polls, "client_pairs": shown}
    return run


@contextlib.contextmanager
def _chromium_page(base: str) -> Iterator[Any]:
    """The page open in headless Chromium (launched before the window, so that the
    browser's start is not in it)."""
    import shutil

    from playwright.sync_api import sync_playwright

    exe = shutil.which("chromium") or shutil.which("chromium-browser")
    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=exe, headless=True,
                                     args=["--no-sandbox", "--disable-gpu"])
        try:
            page = browser.new_page()
            page.goto(base + "/")
            page.wait_for_function("window.trapflow.frames > 0", timeout=60_000)
            yield page
        finally:
            browser.close()


def _page_open(page: Any) -> Callable[[float], dict[str, Any]]:
    def run(seconds: float) -> dict[str, Any]:
        before = page.evaluate("({polls: window.trapflow.polls, frames: window.trapflow.frames})")
        time.sleep(seconds)  # the page polls and draws by itself
        after = page.evaluate("({polls: window.trapflow.polls, frames: window.trapflow.frames})")
        return {"client_polls": after["polls"] - before["polls"],
                "client_pairs": after["frames"] - before["frames"]}
    return run


def bench(seconds: float, warmup: float, client: str) -> dict[str, Any]:
    with _pipeline(("trapflow:broker",)) as ((broker,), run):
        time.sleep(warmup)
        base_w = _window({"broker": broker}, run, seconds)
    per_pair = base_w["broker_cpu_s"] / max(1, base_w["pairs"])
    port = _free_port()
    url = f"http://127.0.0.1:{port}"
    with _pipeline(("trapflow:viewer", "trapflow:broker"), "--view", str(port)) as (
            (viewer, broker), run):
        procs = {"viewer": viewer, "broker": broker}
        time.sleep(warmup)
        closed = _window(procs, run, seconds)
        if client == "http":
            opened = _window(procs, run, seconds, _http_client(url))
        else:
            with _chromium_page(url) as page:
                opened = _window(procs, run, seconds, _page_open(page))
        final = json.loads(_get(f"{url}/api/state"))
    out: dict[str, Any] = {"client": client, "load_average": os.getloadavg(),
                           "baseline": base_w,
                           "broker_cpu_s_per_pair_baseline": round(per_pair, 5)}
    for name, w in (("no_page", closed), ("page_open", opened)):
        extra = w["broker_cpu_s"] - per_pair * w["pairs"]
        w["broker_extra_cpu_s"] = round(extra, 3)
        w["viewer_share"] = round(w["viewer_cpu_s"] / w["window_s"], 4)
        w["broker_extra_share"] = round(extra / w["window_s"], 4)
        w["cost_share"] = round((w["viewer_cpu_s"] + extra) / w["window_s"], 4)
        out[name] = w
    out["pairs_shown"] = final["frames"]["shown"]
    out["previews_received"] = final["frames"]["received"]
    return out


def result(r: dict[str, Any]) -> h.Result:
    b, o = r["baseline"], r["page_open"]
    load = ", ".join(f"{x:.2f}" for x in r["load_average"])
    t = h.Result("viewer", "Live viewer", key="window", data=r, notes=[
        f"Default pipeline (1280x720 raw pairs, 15 pairs/s asked), load average {load} at the "
        f"end; page client: {r['client']}. Shares of one core; the viewer's cost is the "
        "viewer process plus the broker's CPU beyond its baseline per pair "
        f"({1000 * r['broker_cpu_s_per_pair_baseline']:.2f} ms per pair without a viewer, "
        f"{b['rate_hz']} pairs/s, {100 * b['broker_cpu_s'] / b['window_s']:.2f} % of a core).",
        f"With the page open the client made {o['client_polls']} polls and fetched "
        f"{o['client_pairs']} pairs; the viewer received {r['previews_received']} previews."])
    for name, key, budget in (("no page open", "no_page", BUDGET_CLOSED),
                              ("page open", "page_open", BUDGET_OPEN)):
        w = r[key]
        t.add(name, **{"s": h.Figure(w["window_s"], digits=1),
                       "pairs/s": h.Figure(w["rate_hz"]),
                       "viewer": h.Figure(round(100 * w["viewer_share"], 2), "%"),
                       "broker": h.Figure(round(100 * w["broker_cpu_s"] / w["window_s"], 2), "%"),
                       "broker beyond baseline": h.Figure(round(100 * w["broker_extra_share"], 2),
                                                          "%"),
                       "viewer cost": h.Figure(f"**{100 * w['cost_share']:.2f}**", "%"),
                       "budget": h.Figure(f"{100 * budget:g}", "%")})
    return t


def main() -> None:
    ap = h.options(__doc__, repeats=1, quick_help="10 s windows after 8 s")
    ap.add_argument("--seconds", type=float, default=30.0, help="length of each window")
    ap.add_argument("--warmup", type=float, default=15.0, help="seconds after start-up")
    ap.add_argument("--client", choices=("http", "chromium"), default="http",
                    help="the open page: a client polling as it does, or headless Chromium")
    ap.add_argument("--baseline", action="store_true",
                    help="accepted for older command lines: the baseline is always measured")
    args = ap.parse_args()
    if args.quick:
        args.seconds, args.warmup = 10.0, 8.0
    r = bench(args.seconds, args.warmup, args.client)
    results = [result(r)]
    h.write(args.out, "viewer", results)
    print(h.markdown(results))


if __name__ == "__main__":
    main()
