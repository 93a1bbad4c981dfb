"""The viewer's images cost nothing while no page is open: the broker makes its preview only
while a page asks (a client polling as the page does, over HTTP), and stops again once the
page is gone. Real pipeline, real sockets, the broker's own counter read from its status."""

from __future__ import annotations

import signal
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from tests.conftest import Pipeline, poll_for
from tests.integration.viewer_util import attach_viewer, free_port, get, get_json, use_token
from trapflow.viewer.server import PAGE_OPEN_S

pytestmark = pytest.mark.slow  # starts a whole pipeline


def _broker(p: Pipeline) -> dict[str, Any]:
    status = p.status()
    assert status is not None, "the pipeline does not answer"
    counters: dict[str, Any] = next(n for n in status["nodes"]
                                    if n["name"] == "broker")["counters"]
    counters["pairs_in"] = status["stats"]["pairs_in"]
    return counters


def _poll_as_the_page(base: str, seconds: float) -> tuple[int, set[int]]:
    """/api/state twice a second and both images of each new pair, as viewer.js does."""
    end, polls, seqs = time.monotonic() + seconds, 0, set()
    while time.monotonic() < end:
        state = get_json(f"{base}/api/state")
        polls += 1
        frame = state and state["frame"]
        if frame and frame["seq"] not in seqs:
            for side in ("left", "right"):
                code, body = get(f"{base}/frame/{frame['seq']}/{side}.jpg")
                img = cv2.imdecode(np.frombuffer(body, np.uint8), cv2.IMREAD_COLOR)
                assert code == 200 and img is not None and img.std() > 5
                # Reduced for the page: at most 640 wide, the frame's aspect kept.
                assert img.shape[1] <= 640
                assert abs(img.shape[0] / img.shape[1] - frame["height"] / frame["width"]) < 0.01
            seqs.add(frame["seq"])
        time.sleep(0.5)
    return polls, seqs


@pytest.mark.timeout(180)
def test_no_preview_is_made_without_a_page(spawn, run_dir: Path) -> None:
    port = free_port()
    base = f"http://127.0.0.1:{port}"
    p: Pipeline = spawn(["--size", "1280x720", "--view", f"127.0.0.1:{port}"], run_dir)
    use_token(port, run_dir)
    p.wait_active(90)
    # No page: pairs flow for a while, and not one preview is encoded for the viewer.
    start = _broker(p)["pairs_in"]
    poll_for(lambda: _broker(p)["pairs_in"] >= start + 30, 60, interval=1.0,
             what="30 pairs through the broker")
    idle = _broker(p)
    assert idle["previews"] == 0, idle
    code, metrics = get(f"{base}/metrics")  # a scrape is no page: it asks for no images
    assert code == 200 and b"trapflow_pairs_received_total" in metrics
    # A page opens: previews flow at about the viewer's rate (2 per second by default),
    # far fewer than the pairs that reach the broker.
    polls, seqs = _poll_as_the_page(base, 8.0)
    assert len(seqs) >= 3, f"{polls} polls showed {len(seqs)} pairs"
    opened = _broker(p)
    made = opened["previews"]
    assert 3 <= made <= 2.0 * (8.0 + 3 * PAGE_OPEN_S) + 2, opened
    assert made < opened["pairs_in"] - idle["pairs_in"], opened
    assert opened["previews_failed"] == 0
    # The page is gone: after PAGE_OPEN_S the viewer stops asking, the broker stops making.
    time.sleep(PAGE_OPEN_S + 2.0)
    _no_more_previews(p)


def _no_more_previews(p: Pipeline) -> None:
    """20 more pairs go through the broker and it makes no preview; then a clean stop."""
    before = _broker(p)["previews"]
    moved = _broker(p)["pairs_in"]
    poll_for(lambda: _broker(p)["pairs_in"] >= moved + 20, 60, interval=1.0,
             what="20 more pairs through the broker")
    assert _broker(p)["previews"] == before
    code, _, err = p.stop()
    assert code == 0, err


@pytest.mark.timeout(180)
def test_a_viewer_killed_with_its_page_open_leaves_no_previews(spawn, run_dir: Path,
                                                               started_procs) -> None:
    """A `trapflow view` killed (-9) while its page was open: the broker's tap hears the
    subscriber go (libzmq unsubscribes a peer whose connection ended) and makes no more
    previews for nobody."""
    p: Pipeline = spawn(["--size", "640x360"], run_dir)
    p.wait_active(90)
    view, port = attach_viewer(run_dir, started_procs, quiet=True)
    poll_for(lambda: get_json(f"http://127.0.0.1:{port}/api/state"), 40, interval=0.5,
             what="the viewer answering")
    _, seqs = _poll_as_the_page(f"http://127.0.0.1:{port}", 4.0)
    assert seqs and _broker(p)["previews"] >= 2
    view.send_signal(signal.SIGKILL)
    view.wait(10)
    time.sleep(2.0)  # the broker hears of it when it next sends on its tap (stats: 1/s)
    _no_more_previews(p)
