"""Helpers of the viewer tests: a free port, HTTP without a client library, the browser.

Every viewer asks for its token, loopback included (issue 36 item 3). The viewers the tests
start take the harness's own token from the environment (tests/conftest.py sets
TRAPFLOW_VIEWER_TOKEN, as an operator may): `use_token` says a port is one of them, and
get, get_json and post to that port send the token; `page_url` is the address a browser
opens (with ?token=, as the console prints it)."""

from __future__ import annotations

import importlib.util
import json
import os
import shutil
import socket
import subprocess
import sys
import urllib.error
import urllib.request
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

from trapflow.viewer.access import TOKEN_ENV

# Launch flags that work in a container without a display, GPU or network.
CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update",
                 "--disable-sync"]


_PORTS: set[int] = set()  # the ports of viewers the tests started


def use_token(port: int, run_dir: Path | None = None) -> None:
    """get, get_json and post to this port send the harness's viewer token."""
    _PORTS.add(port)


def token_of(port: int) -> str | None:
    """The token of a viewer the tests started at this port."""
    return os.environ[TOKEN_ENV] if port in _PORTS else None


def page_url(port: int, run_dir: Path) -> str:
    """The page's address with its token, as the console of the user who started it shows."""
    use_token(port, run_dir)
    return f"http://127.0.0.1:{port}/?token={token_of(port)}"


def _with_token(url: str, headers: dict[str, str] | None) -> dict[str, str]:
    out = dict(headers or {})
    token = token_of(urlsplit(url).port or 80)
    if token is not None and "Authorization" not in out:
        out["Authorization"] = f"Bearer {token}"
    return out


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
         f"127.0.0.1:{port}"], stdout=out, stderr=out, cwd=REPO,
        env={**os.environ, "PYTHONFAULTHANDLER": "1"})  # SIGABRT dumps its threads' stacks
    started.append(view)
    use_token(port, run_dir)
    return view, port


def get(url: str, timeout: float = 2.0, headers: dict[str, str] | None = None
        ) -> tuple[int, bytes]:
    """Status and body of a GET (with the port's viewer token, if any); (0, b"") when
    nothing answers."""
    req = urllib.request.Request(url, headers=_with_token(url, headers))
    try:
        with urllib.request.urlopen(req, timeout=timeout) as r:
            return r.status, r.read()
    except urllib.error.HTTPError as exc:
        return exc.code, exc.read()
    except OSError:
        return 0, b""


def get_json(url: str) -> Any:
    code, body = get(url)
    return json.loads(body) if code == 200 else None


def post(url: str, headers: dict[str, str] | None = None) -> int:
    req = urllib.request.Request(url, data=b"", method="POST", headers=_with_token(url, headers))
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
