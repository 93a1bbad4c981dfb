"""What the README promises of the command line, with real processes: `trapflow process`
fails in one line on stderr, `trapflow start --view` prints the page's address."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import Pipeline, poll_for, run_process
from tests.integration.viewer_util import free_port, get, post, use_token
from trapflow.viewer.access import TOKEN_ENV


@pytest.mark.timeout(150)
def test_process_error_is_one_line_without_dask_tracebacks(tmp_path: Path) -> None:
    """Regression (issue 22, item 8): an input that cannot be read gave 23 lines on stderr,
    3 of them Dask's tracebacks of the same error (one per retry)."""
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(bytes(range(256)) * 20)
    code, out, err = run_process([str(junk), "--workers", "mono", "--out",
                                  str(tmp_path / "out"), "--local", "1"])
    assert code == 1, err
    errors = [line for line in err.splitlines() if "error" in line.lower()]
    assert len(errors) == 1 and errors[0].startswith("trapflow: error: "), err
    assert "cannot read" in errors[0] and "ledger.json" in errors[0], err
    assert "Traceback" not in err and "distributed." not in err, err
    assert "junk.mcap" in out  # the summary table still names the input


@pytest.mark.slow  # starts a whole pipeline
@pytest.mark.timeout(150)
def test_start_view_prints_the_page_address_and_keeps_its_token_private(
        spawn, run_dir: Path) -> None:
    """Regression (issue 22, item 8): `trapflow start --view PORT` served the page but never
    said where; the address was only in trapflow.log. Issue 36 items 3 and 4: on loopback
    no token was asked (another local user read frames, switched a pool off, stopped the
    pipeline), and the token of a viewer was in trapflow.log (`viewer: active
    (http://...?token=...)`), in `trapflow status` (text and JSON) and in /api/state."""
    port = free_port()
    p: Pipeline = spawn(["--workers", "vo=1", "--size", "160x120", "--view", str(port)],
                        run_dir)
    p.wait_active(90)
    token = os.environ[TOKEN_ENV]  # the harness's (an operator's may come the same way)
    base = f"http://127.0.0.1:{port}"
    # Without the token (another local user): neither reads nor controls.
    assert get(f"{base}/api/state")[0] == 401
    assert get(f"{base}/frame/1/left.jpg")[0] == 401
    assert post(f"{base}/api/stop", {"X-Trapflow-Control": "stop"}) == 401
    assert post(f"{base}/api/pool?pool=vo&active=0", {"X-Trapflow-Control": "pool"}) == 401
    # With it: the state, which does not carry it.
    use_token(port, run_dir)
    code, body = poll_for(lambda: (r := get(f"{base}/api/state"))[0] == 200
                          and json.loads(r[1])["nodes"] and r, 30, interval=0.5,
                          what="the state with its nodes")
    assert token.encode() not in body and b"printed on the console" in body
    status = p.status()
    assert status is not None and token not in json.dumps(status)
    viewer = next(n for n in status["nodes"] if n["name"] == "viewer")
    assert "printed on the console" in viewer["reason"]
    text = subprocess.run([sys.executable, "-m", "trapflow", "status", "--run-dir",
                           str(run_dir)], capture_output=True, text=True, timeout=60)
    assert text.returncode == 0 and "viewer" in text.stdout, text.stderr
    assert token not in text.stdout + text.stderr
    code, out, err = p.stop()
    assert code == 0, err
    shown = [line for line in out.splitlines() if line.startswith("viewer: ")]
    assert shown == [f"viewer: {base}/?token={token}"], out  # the starting user's console
    assert out.index("starting") < out.index("viewer: ")  # printed while it starts
    # No file of the run directory has it (trapflow.log, status.json, ledger.json, ...).
    kept = [f.name for f in run_dir.rglob("*") if f.is_file() and token.encode() in f.read_bytes()]
    assert kept == []
    logs = "".join(f.read_text() for f in run_dir.glob("trapflow.log*"))
    assert "viewer" in logs and token not in logs and token not in err
