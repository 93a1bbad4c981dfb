"""Slow clients against the viewer, over real TCP (Viewer.start on a loopback port): clients
that send half a request and wait are closed, and the page still answers meanwhile.

Regression for issue 26 item 10: the viewer never timed out slow clients (400 held for
60 s, each a connection and its buffers).
"""

from __future__ import annotations

import asyncio
import socket
import time
from pathlib import Path

import pytest

from tests.reliability import figures
from trapflow.config.schema import Config
from trapflow.viewer.server import IDLE_S, Viewer

SLOW = 200  # clients that send half a request and wait


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


async def _get_state(port: int, token: str) -> bytes:
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    writer.write(f"GET /api/state HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n"
                 f"Authorization: Bearer {token}\r\nConnection: close\r\n\r\n".encode())
    data = await asyncio.wait_for(reader.read(), 5.0)
    writer.close()
    return data


@pytest.mark.timeout(60)
def test_half_requests_are_closed_and_the_page_still_answers(tmp_path: Path) -> None:
    async def main() -> tuple[int, float, bytes]:
        (tmp_path / "run").mkdir()
        v = Viewer(Config(), tmp_path / "run", "a-token-of-this-test-0123")
        port = _free_port()
        runner = await v.start("127.0.0.1", port)
        slow: list[asyncio.StreamReader] = []
        writers = []
        try:
            for i in range(SLOW):  # the request line and a header, never the blank line
                reader, writer = await asyncio.open_connection("127.0.0.1", port)
                writer.write(f"GET /api/state HTTP/1.1\r\nX-Slow: {i}\r\n".encode())
                slow.append(reader)
                writers.append(writer)
            t0 = time.monotonic()
            answer = await _get_state(port, v.access.token)  # a real reader is answered meanwhile

            async def closed(r: asyncio.StreamReader) -> bool:
                try:
                    await asyncio.wait_for(r.read(), IDLE_S + 10.0)
                    return True  # EOF (or a 4xx and EOF): the server let it go
                except (TimeoutError, ConnectionError):
                    return False

            results = await asyncio.gather(*(closed(r) for r in slow))
            waited = time.monotonic() - t0
            return sum(results), waited, answer
        finally:
            for w in writers:
                w.close()
            await runner.cleanup()
            v.close()

    n_closed, waited, answer = asyncio.run(main())
    figures("viewer_slow_clients", clients=SLOW, closed=n_closed, seconds=round(waited, 1))
    assert answer.startswith(b"HTTP/1.1 200"), answer[:80]
    assert n_closed == SLOW, f"{SLOW - n_closed} of {SLOW} slow clients still held"
    assert waited < IDLE_S + 10.0
