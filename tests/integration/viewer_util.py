"""Helpers of the viewer tests: a free port, HTTP without a client library, the browser."""

from __future__ import annotations

import importlib.util
import json
import shutil
import socket
import subprocess
import sys
import urllib.error
import urllib.request
from pathlib import Path
from typing import Any

# Launch flags that work in a container without a display, GPU or network.
CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update",
                 "--disable-sync"]


def free_port() -> int:
    """A TCP port nothing listens on right now (the kernel's pick)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


def attach_viewer(run_dir: Path, started: list[subprocess.Popen[bytes]],
                  quiet: bool = False) -> tuple[subprocess.Popen[bytes], int]:
    """`trapflow view` attached to a running pipeline's run directory on a free loopback
    port, recorded in `started` (the harness kills what is left); its output piped, or
    discarded when quiet."""
    from tests.conftest import REPO

    port = free_port()
    out = subprocess.DEVNULL if quiet else subprocess.PIPE
    view = subprocess.Popen(
        [sys.executable, "-m", "trapflow", "view", "--run-dir", str(run_dir), "--listen",
         f"127.0.0.1:{port}"], stdout=out, stderr=out, cwd=REPO)
    started.append(view)
    return view, port


def get(url: str, timeout: float = 2.0) -> tuple[int, bytes]:
    """Status and body of a GET; (0, b"") when nothing answers."""
    try:
        with urllib.request.urlopen(url, timeout=timeout) as r:
            return r.status, r.read()
    except urllib.error.HTTPError as exc:
        return exc.code, exc.read()
    except OSError:
        return 0, b""


def get_json(url: str) -> Any:
    code, body = get(url)
    return json.loads(body) if code == 200 else None


def post(url: str, headers: dict[str, str] | None = None) -> int:
    req = urllib.request.Request(url, data=b"", method="POST", headers=headers or {})
    try:
        with urllib.request.urlopen(req, timeout=2.0) as r:
            status: int = r.status
            return status
    except urllib.error.HTTPError as exc:
        return exc.code


def chromium() -> str | None:
    """The Chromium binary of the system's package, if installed."""
    for name in ("chromium", "chromium-browser"):
        path = shutil.which(name)
        if path:
            return path
    return None


def browser_skip_reason() -> str | None:
    """Why the browser tests cannot run here, or None."""
    if chromium() is None:
        return "no Chromium installed (apt-get install chromium)"
    if importlib.util.find_spec("playwright") is None:
        return "the playwright package is not installed (pip install -e '.[test]')"
    return None


def profile_dir(base: Path) -> Path:
    """A fresh --user-data-dir for one browser."""
    d = base / "chromium-profile"
    d.mkdir(parents=True, exist_ok=True)
    return d
