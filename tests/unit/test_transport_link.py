"""Local links: real UNIX seqpacket sockets, one datagram per message, EOF as LinkClosed."""

from __future__ import annotations

from pathlib import Path

import pytest

from trapflow.errors import ProtocolError
from trapflow.wire.links import LinkClosed, accept_link, connect_link, listen_link


@pytest.fixture
def link_path(tmp_path_factory: pytest.TempPathFactory) -> str:
    return str(tmp_path_factory.mktemp("lk") / "test.link")  # short: UNIX paths are limited


def test_messages_keep_their_frames_and_order(link_path: str) -> None:
    listener = listen_link(link_path)
    client = connect_link(link_path)
    server = accept_link(listener)
    assert server is not None
    assert server.recv() is None  # nothing waiting: no block, no error
    for i in range(50):
        assert client.send([b"done", str(i).encode(), b"r" * i])
    got = []
    while server.wait(1000) and (frames := server.recv()) is not None:
        got.append([bytes(f) for f in frames])
        if len(got) == 50:
            break
    assert got == [[b"done", str(i).encode(), b"r" * i] for i in range(50)]
    assert server.send([b"job"]) and client.wait(1000)
    assert [bytes(f) for f in client.recv() or []] == [b"job"]
    client.close()
    server.close()
    listener.close()


def test_peer_exit_is_link_closed_and_a_new_listener_replaces_a_stale_file(
        link_path: str) -> None:
    listener = listen_link(link_path)
    client = connect_link(link_path)
    server = accept_link(listener)
    assert server is not None
    client.close()
    assert server.wait(1000)
    with pytest.raises(LinkClosed, match="closed by its peer"):
        server.recv()
    with pytest.raises(LinkClosed):
        server.send([b"x"])
    listener.close()  # a crashed broker leaves its socket file behind
    assert Path(link_path).exists()
    with pytest.raises(LinkClosed, match="cannot connect"):
        connect_link(link_path)
    listener = listen_link(link_path)  # its successor replaces it
    again = connect_link(link_path)
    assert again is not None
    for end in (again, server, listener):
        end.close()


def test_a_garbled_datagram_is_a_protocol_error_not_a_crash(link_path: str) -> None:
    listener = listen_link(link_path)
    client = connect_link(link_path)
    server = accept_link(listener)
    assert server is not None
    client.sock.send(b"\x03garbage")
    assert server.wait(1000)
    with pytest.raises(ProtocolError, match="link message"):
        server.recv()
    assert client.send([b"fine"]) and server.wait(1000)
    assert [bytes(f) for f in server.recv() or []] == [b"fine"]
    for end in (client, server, listener):
        end.close()


def test_messages_sent_before_a_reset_are_still_read(link_path: str) -> None:
    """Pins a loss at a worker's exit: a worker answered its last pair, said goodbye and
    exited with a job of the broker's unread. Linux then reports ECONNRESET once, ahead of
    the answer and the goodbye still queued; the broker took it for the end of the link,
    never read them, and counted the pair lost ("disconnected")."""
    listener = listen_link(link_path)
    client = connect_link(link_path)
    server = accept_link(listener)
    assert server is not None
    assert server.send([b"job"])  # never read by the client
    assert client.send([b"done", b"result"]) and client.send([b"gone"])
    client.close()
    assert server.wait(1000)
    assert [bytes(f) for f in server.recv() or []] == [b"done", b"result"]
    assert [bytes(f) for f in server.recv() or []] == [b"gone"]
    with pytest.raises(LinkClosed, match="closed by its peer"):
        server.recv()
    server.close()
    listener.close()
