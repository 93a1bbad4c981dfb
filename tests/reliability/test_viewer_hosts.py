"""The viewer under forged Host headers and without its token, over real HTTP (the
viewer's aiohttp application on an ephemeral loopback port).

Regression for issue 26 item 2: on loopback, /api/state, frames and /metrics answered a
foreign Host (readable by a DNS-rebinding page), and a bind to 0.0.0.0 asked for nothing,
so anyone on the network (or a rebinding page) could stop the pipeline; and issue 36 item 3:
on loopback no token was asked, so another user of the machine read live frames, switched
a pool off and stopped the pipeline.
"""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable
from pathlib import Path

import pytest
from aiohttp.test_utils import TestClient, TestServer

from trapflow.config.schema import Config, ViewerConfig
from trapflow.viewer.access import COOKIE, console_address, new_token
from trapflow.viewer.server import CONTROL_HEADER, Viewer
from trapflow.viewer.state import Frame

TOKEN = "s3cret-token-of-the-test-0123456789"
READS = ("/", "/api/state", "/frame/1/left.jpg", "/metrics", "/static/viewer.js")

Body = Callable[[TestClient, Viewer], Awaitable[None]]


def with_viewer(tmp_path: Path, body: Body, **viewer: object) -> None:
    """Run body against a Viewer served on 127.0.0.1 at an ephemeral port."""
    cfg = Config(viewer=ViewerConfig(**viewer))  # type: ignore[arg-type]

    async def main() -> None:
        (tmp_path / "run").mkdir(exist_ok=True)
        v = Viewer(cfg, tmp_path / "run", new_token())
        v.state.shown = Frame(seq=1, width=2, height=2, left=b"\xff\xd8L",
                              right=b"\xff\xd8R", t_wall_ns=0)
        client = TestClient(TestServer(v.app, host="127.0.0.1"))
        await client.start_server()
        try:
            await body(client, v)
        finally:
            await client.close()
            v.close()

    asyncio.run(main())


async def status(client: TestClient, method: str, path: str, **headers: str) -> int:
    async with client.request(method, path, headers=headers, allow_redirects=False) as r:
        await r.read()
        return r.status


@pytest.mark.timeout(30)
def test_loopback_refuses_foreign_hosts_for_reads_and_writes(tmp_path: Path) -> None:
    async def body(client: TestClient, v: Viewer) -> None:
        port = client.port
        for host in ("evil.example", f"evil.example:{port}", f"localhost.evil.example:{port}",
                     f"192.168.1.20:{port}"):
            for path in READS:
                assert await status(client, "GET", path, Host=host) == 403, (host, path)
            assert await status(client, "POST", "/api/stop", Host=host,
                                **{CONTROL_HEADER: "stop"}) == 403
            assert await status(client, "POST", "/api/pool", Host=host,
                                **{CONTROL_HEADER: "pool"}) == 403
        async with client.get("/api/state", headers={"Host": "evil.example"}) as r:
            assert "not one of the viewer's names" in await r.text()
        # the viewer's own names read with the token; without it, another local user
        # neither reads nor drives it (issue 36 item 3)
        bearer = f"Bearer {v.access.token}"
        for host in (f"127.0.0.1:{port}", f"localhost:{port}", f"[::1]:{port}"):
            for path in READS:
                assert await status(client, "GET", path, Host=host) == 401, (host, path)
                assert await status(client, "GET", path, Host=host,
                                    Authorization=bearer) == 200, (host, path)
            for path, header in (("/api/stop", "stop"), ("/api/pool", "pool")):
                assert await status(client, "POST", path, Host=host,
                                    **{CONTROL_HEADER: header}) == 401, (host, path)
        # the address the node's state carries says where the token is, never the token
        assert v.url("127.0.0.1", port) == (f"http://127.0.0.1:{port}/ (token: printed on "
                                            "the console that started the viewer)")
        assert v.access.token not in v.url("127.0.0.1", port)
        assert not any(v.access.token.encode() in f.read_bytes()
                       for f in (tmp_path / "run").rglob("*") if f.is_file())

    with_viewer(tmp_path, body)


@pytest.mark.timeout(30)
def test_configured_host_name_is_allowed(tmp_path: Path) -> None:
    async def body(client: TestClient, v: Viewer) -> None:
        assert await status(client, "GET", "/api/state", Host="trap.lan:8090",
                            Authorization=f"Bearer {v.access.token}") == 200
        assert await status(client, "GET", "/api/state", Host="evil.example:8090") == 403

    with_viewer(tmp_path, body, allowed_hosts=["trap.lan"])


@pytest.mark.timeout(30)
def test_off_loopback_a_token_is_needed(tmp_path: Path) -> None:
    token_file = tmp_path / "token"
    token_file.write_text(TOKEN + "\n")
    token_file.chmod(0o600)

    async def body(client: TestClient, v: Viewer) -> None:
        host = f"192.168.1.20:{client.port}"
        # no token, or a wrong one: refused, reads and writes
        for path in READS:
            assert await status(client, "GET", path, Host=host) == 401, path
            assert await status(client, "GET", path, Host=host,
                                Authorization="Bearer wrong-token-0123456789") == 401, path
        assert await status(client, "POST", "/api/stop", Host=host,
                            **{CONTROL_HEADER: "stop"}) == 401
        assert await status(client, "GET", f"/api/state?token={TOKEN}", Host=host) == 401
        # a foreign Host is refused even with the token
        assert await status(client, "GET", "/api/state", Host="evil.example",
                            Authorization=f"Bearer {TOKEN}") == 403
        # the header opens every read (scripts, Prometheus)
        for path in READS:
            assert await status(client, "GET", path, Host=host,
                                Authorization=f"Bearer {TOKEN}") == 200, path
        # the page with ?token=: a cookie (HttpOnly, SameSite=Strict) and the address without
        async with client.get(f"/?token={TOKEN}", headers={"Host": host},
                              allow_redirects=False) as r:
            assert r.status == 303 and r.headers["Location"] == "/"
            cookie = r.headers["Set-Cookie"]
        assert f"{COOKIE}={TOKEN}" in cookie and "HttpOnly" in cookie
        assert "SameSite=Strict" in cookie
        # the cookie alone then opens the reads the page makes
        for path in READS:
            assert await status(client, "GET", path, Host=host,
                                Cookie=f"{COOKIE}={TOKEN}") == 200, path
        assert console_address(v.url("0.0.0.0", 8090), v.access.token).endswith(
            f"(token: the contents of {token_file})")

    with_viewer(tmp_path, body, host="0.0.0.0", token_file=str(token_file))


@pytest.mark.timeout(30)
def test_off_loopback_without_a_file_a_token_is_made_and_printed(tmp_path: Path) -> None:
    async def body(client: TestClient, v: Viewer) -> None:
        assert v.access.token not in v.url("0.0.0.0", 8090)
        url = console_address(v.url("0.0.0.0", 8090), v.access.token)
        assert url.startswith("http://0.0.0.0:8090/?token=")
        token = url.split("=", 1)[1]
        assert len(token) >= 32 and token == v.access.token
        host = f"127.0.0.1:{client.port}"
        assert await status(client, "GET", "/api/state", Host=host) == 401
        assert await status(client, "GET", "/api/state", Host=host,
                            Authorization=f"Bearer {token}") == 200

    with_viewer(tmp_path, body, host="0.0.0.0")
