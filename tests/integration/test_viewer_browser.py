"""The live viewer in a real browser (headless Chromium) against a running pipeline."""

from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from tests.conftest import Pipeline, write_config
from tests.integration.viewer_util import (
    CHROMIUM_ARGS,
    browser_skip_reason,
    chromium,
    free_port,
    page_url,
    profile_dir,
)

pytestmark = [pytest.mark.skipif(browser_skip_reason() is not None,
                                 reason=str(browser_skip_reason())),
              pytest.mark.slow]  # starts whole pipelines and a browser

BOX_BGR = np.array([51, 221, 255])  # the page draws detections in #ffdd33


@pytest.fixture
def page(run_dir: Path) -> Iterator[Any]:
    """A page of a headless Chromium with a fresh profile, closed after the test."""
    from playwright.sync_api import sync_playwright

    with sync_playwright() as pw:
        ctx = pw.chromium.launch_persistent_context(
            str(profile_dir(run_dir.parent)), executable_path=chromium(), headless=True,
            args=CHROMIUM_ARGS, viewport={"width": 1400, "height": 1000})
        try:
            yield ctx.new_page()
        finally:
            ctx.close()


def _start(spawn: Any, run_dir: Path, *args: str) -> tuple[Pipeline, str]:
    port = free_port()
    p: Pipeline = spawn(["--size", "640x360", "--view", f"127.0.0.1:{port}", *args], run_dir)
    p.wait_active(90)
    return p, page_url(port, run_dir)


@pytest.mark.timeout(150)
def test_page_draws_a_detected_box_and_moving_charts(spawn, run_dir: Path, page: Any) -> None:
    cfg = write_config(run_dir.parent / "events.yaml", {"events": {
        "enabled": True, "pre_s": 0.5, "post_s": 1.0,
        "triggers": [{"algorithm": "mono_ir", "label": "crab"}]}})
    p, url = _start(spawn, run_dir, "--config", str(cfg))
    page.goto(url)
    # A pair with at least one drawn detection box, from the synthetic crabs.
    page.wait_for_function("window.trapflow.frames > 0 && window.trapflow.boxes > 0",
                           timeout=60_000)
    chart = "#pool-mono canvas.rate"
    before = int(page.get_attribute(chart, "data-points"))
    page.wait_for_function(
        f"Number(document.querySelector('{chart}').dataset.points) > {before}",
        timeout=10_000)
    # the node's name cell (its reason names the token file, viewer.token, too)
    assert page.locator("#nodes td", has_text=re.compile(r"^viewer$")).count() == 1
    assert "processed" in page.inner_text("#ledger")
    # The power model's estimate (issue 25): watts and Wh per day from the run's CPU so far.
    page.wait_for_function("/energy \\(\\w+ model\\).* W, .* Wh\\/day/"
                           ".test(document.getElementById('ledger').innerText)", timeout=20_000)
    # An event folder written by the events node, shown with its first image as thumbnail.
    page.wait_for_function(
        "[...document.querySelectorAll('#events img')].some(i => i.complete && i.naturalWidth)",
        timeout=30_000)
    png = page.locator("#left").screenshot()
    img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    assert img is not None and img.shape[1] >= 320
    assert float(img.std()) > 10.0, "the left image is blank"
    near_box = np.abs(img.astype(int) - BOX_BGR).max(axis=2) < 40
    assert int(near_box.sum()) > 50, "no detection box drawn on the left image"
    shot = run_dir.parent / "viewer.png"
    page.screenshot(path=str(shot), full_page=True)
    full = cv2.imread(str(shot))
    assert full is not None and float(full.std()) > 10.0
    assert p.proc.poll() is None


@pytest.mark.timeout(150)
def test_stop_button_stops_the_pipeline(spawn, run_dir: Path, page: Any) -> None:
    p, url = _start(spawn, run_dir)
    page.goto(url)
    page.wait_for_function("window.trapflow.polls > 0", timeout=20_000)
    page.click("#stop")
    page.wait_for_function("document.getElementById('stop').textContent.includes('stopping')",
                           timeout=10_000)
    code, out, err = p.wait(30)
    assert code == 0, err
    assert "totals:" in out and (run_dir / "ledger.json").exists()
    assert "stop requested from the viewer" in (run_dir / "trapflow.log").read_text()


def _control(page: Any, attr: str, value: str, timeout: int = 30_000) -> None:
    page.wait_for_function(
        f"document.querySelector('#pool-mono .ctl')?.dataset.{attr} === '{value}'",
        timeout=timeout)


@pytest.mark.timeout(150)
def test_pool_buttons_drive_runtime_control(spawn, run_dir: Path, page: Any) -> None:
    """The pool's buttons change it as `trapflow pool` does: deactivate, activate, one
    worker more; the page shows the pool's control state, its last change, the ledger's
    pairs in progress and the degradation ladder's level."""
    p, url = _start(spawn, run_dir)
    page.goto(url)
    ctl = "#pool-mono .ctl"
    _control(page, "state", "active")
    count = int(page.get_attribute(ctl, "data-count"))
    assert "policy" in page.inner_text(f"{ctl} .ctl-text")
    page.wait_for_function("document.getElementById('ledger').innerText.includes('in progress')",
                           timeout=10_000)
    # The default ladder's level (full on a bench, unless this machine's disk or heat moved it).
    page.wait_for_function("document.getElementById('level').dataset.level", timeout=10_000)
    assert page.locator("#level").is_visible()
    status = p.status()
    assert status is not None
    assert page.get_attribute("#level", "data-level") in status["supervision"]["ladder"]["levels"]

    page.click(f"{ctl} button.toggle")
    _control(page, "state", "inactive")
    assert "deactivated" in page.inner_text(f"{ctl} .ctl-reply")
    assert page.inner_text(f"{ctl} button.toggle") == "Activate"
    page.wait_for_function("document.querySelector('#pool-mono .ctl-text').textContent"
                           ".includes('last change at')", timeout=10_000)
    page.click(f"{ctl} button.toggle")
    _control(page, "state", "active")
    page.click(f"{ctl} button.more")
    _control(page, "count", str(count + 1))
    assert f"count {count} -> {count + 1}" in page.inner_text(f"{ctl} .ctl-reply")

    st = p.status()
    assert st is not None
    sup = st["supervision"]
    assert sup["control"] == 3
    assert sup["pools"]["mono"]["state"] == "active"
    assert sup["pools"]["mono"]["count"] == count + 1
    assert "pool change requested" in (run_dir / "trapflow.log").read_text()


MOTION_RGB = (255, 102, 204)  # the page draws moving regions in #ff66cc


@pytest.mark.timeout(180)
def test_page_shows_tracks_measures_counts_motion_and_gate(spawn, run_dir: Path,
                                                           page: Any) -> None:
    """Issues 23-25 on the page: each box with its track's id and what the stereo pair
    measured (range and length, or why not), a live count per label, the motion gate's
    moving regions and whether a gated pool is withheld pairs now."""
    cfg = write_config(run_dir.parent / "gated.yaml", {"pools": {"stereo": {"gate": "motion"}}})
    p, url = _start(spawn, run_dir, "--config", str(cfg))
    page.goto(url)
    page.wait_for_function("window.trapflow.tracks.length > 0", timeout=90_000)
    tracked = page.locator("#boxes li.det:not([data-track=''])").first
    track = int(tracked.get_attribute("data-track"))
    assert tracked.inner_text().startswith(f"#{track} ")
    # A measured box says its range and length with their sd (or why it is unmeasured).
    page.wait_for_function("[...document.querySelectorAll('#boxes .measure')]"
                           ".some(m => /^range \\d+\\.\\d\\d m ± \\d/.test(m.textContent))",
                           timeout=60_000)
    measures = page.locator("#boxes .measure").all_inner_texts()
    assert all(m.startswith(("range ", "unmeasured: ")) for m in measures), measures
    # A live count per label, with visits and MaxN.
    page.wait_for_function("document.querySelector('#counts tr[data-label]')", timeout=10_000)
    row = page.locator("#counts tr[data-label]").first
    assert int(row.locator(".visits").inner_text()) >= 1
    assert int(row.locator(".maxn").inner_text()) >= 1
    # The gate's moving regions drawn on the left image: its pixels read in the same tick
    # as the number of regions it was drawn with (the page redraws twice a second).
    drawn = page.wait_for_function("""(rgb) => {
        const c = document.getElementById('left');
        if (!(Number(c.dataset.motion) > 0)) return false;
        const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
        let n = 0;
        for (let i = 0; i < d.length; i += 4)
          if (Math.abs(d[i] - rgb[0]) < 40 && Math.abs(d[i + 1] - rgb[1]) < 40 &&
              Math.abs(d[i + 2] - rgb[2]) < 40) n++;
        return n > 20 && n;
    }""", arg=list(MOTION_RGB), timeout=60_000).json_value()
    assert drawn > 20, "no motion region drawn on the left image"
    # The gated pool says whether its gate withholds pairs now, with the broker's count.
    page.wait_for_function("!document.querySelector('#pool-stereo .gate')?.hidden",
                           timeout=30_000)
    gate = page.locator("#pool-stereo .gate")
    assert gate.get_attribute("data-gated") in ("now", "open")
    assert "withheld" in gate.inner_text()
    assert page.locator("#pool-vo .gate").is_hidden()  # VO is never gated
    # The ids the page drew are the normalizer's: the same track on a written line.
    code, _, err = p.stop()
    assert code == 0, err
    assert any(r.get("mono_ir", {}).get("track") == track for r in p.results())
