"""The broker's poller: real zmq sockets and local links, one poll() for all of them."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
import zmq

from trapflow.wire.links import Poller, accept_link, connect_link, listen_link
from trapflow.wire.transport import zmq_readable

Sockets = tuple[zmq.Socket[bytes], zmq.Socket[bytes]]


@pytest.fixture
def pair(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Sockets]:
    """A bound PULL and a connected PUSH over ipc, closed after the test."""
    ctx = zmq.Context()
    where = tmp_path_factory.mktemp("pl") / "p.sock"
    pull = ctx.socket(zmq.PULL)
    pull.bind(f"ipc://{where}")
    push = ctx.socket(zmq.PUSH)
    push.connect(f"ipc://{where}")
    yield push, pull
    ctx.destroy(linger=0)


def _wait_readable(sock: zmq.Socket[bytes]) -> None:
    deadline = time.monotonic() + 5
    while not zmq_readable(sock):
        assert time.monotonic() < deadline, "message never arrived"
        time.sleep(0.01)


def test_a_message_that_arrived_before_registering_is_reported(pair: Sockets) -> None:
    push, pull = pair
    push.send(b"early")
    _wait_readable(pull)  # reading EVENTS here consumes the notification the poller would see
    poller = Poller()
    poller.register(pull)
    socks, fds = poller.poll(0)
    assert socks == [pull] and fds == []
    assert pull.recv() == b"early"


def test_a_message_wakes_a_sleeping_poll_and_an_idle_poll_times_out(pair: Sockets) -> None:
    push, pull = pair
    poller = Poller()
    poller.register(pull)
    assert poller.poll(50) == ([], [])  # nothing waiting: the timeout, then nothing reported
    sender = threading.Timer(0.2, lambda: push.send(b"late"))
    sender.start()
    try:
        socks: list[zmq.Socket[bytes]] = []
        deadline = time.monotonic() + 5
        while not socks and time.monotonic() < deadline:  # a wake-up may be for a command
            socks, _ = poller.poll(5000)
        assert socks == [pull]
        assert pull.recv() == b"late"
    finally:
        sender.join()


def test_a_touched_socket_is_checked_again_after_a_partial_drain(pair: Sockets) -> None:
    push, pull = pair
    poller = Poller()
    poller.register(pull)
    push.send(b"one")
    push.send(b"two")
    _wait_readable(pull)
    time.sleep(0.1)  # let "two" arrive too
    assert pull.recv() == b"one"  # a receive may consume the notification of "two"
    poller.touch(pull)
    deadline = time.monotonic() + 5
    socks: list[zmq.Socket[bytes]] = []
    while not socks and time.monotonic() < deadline:
        socks, _ = poller.poll(0)
    assert socks == [pull]
    assert pull.recv() == b"two"
    assert not zmq_readable(pull)


def test_links_and_listeners_are_reported_by_descriptor(tmp_path: Path) -> None:
    path = str(tmp_path / "t.link")
    listener = listen_link(path)
    poller = Poller()
    poller.register(listener)
    client = connect_link(path)
    assert poller.poll(1000) == ([], [listener.fileno()])  # a peer waits to be accepted
    server = accept_link(listener)
    assert server is not None
    poller.register(server)
    assert client.send([b"hello"])
    assert poller.poll(1000) == ([], [server.fileno()])
    assert [bytes(f) for f in server.recv() or []] == [b"hello"]
    poller.unregister(server)
    assert client.send([b"unwatched"])
    assert poller.poll(50) == ([], [])  # an unregistered link is no longer watched
    for s in (client, server):
        s.close()
    listener.close()
