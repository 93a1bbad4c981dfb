"""Message-size caps on bound sockets and the tap's subscription gate, over real ipc
sockets (issue 16 item 7)."""

from __future__ import annotations

import time
from pathlib import Path

import pytest
import zmq

from tests.conftest import poll_for
from trapflow.wire import tap_gate, transport
from trapflow.wire.tap_gate import TapGate
from trapflow.wire.transport import SocketSpec, open_socket


@pytest.mark.parametrize(("kind", "cap"), [
    (zmq.XPUB, transport.TAP_MAX_MSG_BYTES),
    (zmq.PUB, transport.TAP_MAX_MSG_BYTES),
    (zmq.PULL, transport.SMALL_MAX_MSG_BYTES),
    (zmq.REP, transport.SMALL_MAX_MSG_BYTES),
    (zmq.ROUTER, transport.WORKERS_MAX_MSG_BYTES),
])
def test_every_bound_socket_caps_its_messages(zctx, tmp_path: Path, kind: int, cap: int) -> None:
    sock = open_socket(zctx, SocketSpec(kind, f"ipc://{tmp_path / 's'}", bind=True))
    try:
        assert sock.getsockopt(zmq.MAXMSGSIZE) == cap
    finally:
        sock.close(linger=0)


def test_explicit_cap_wins_and_connecting_sockets_have_none(zctx, tmp_path: Path) -> None:
    ep = f"ipc://{tmp_path / 's'}"
    pull = open_socket(zctx, SocketSpec(zmq.PULL, ep, bind=True, max_msg_bytes=12345))
    push = open_socket(zctx, SocketSpec(zmq.PUSH, ep))
    try:
        assert pull.getsockopt(zmq.MAXMSGSIZE) == 12345
        assert push.getsockopt(zmq.MAXMSGSIZE) == -1
    finally:
        pull.close(linger=0)
        push.close(linger=0)


def test_a_message_over_the_cap_never_arrives(zctx, tmp_path: Path) -> None:
    ep = f"ipc://{tmp_path / 'hb'}"
    pull = open_socket(zctx, SocketSpec(zmq.PULL, ep, bind=True))
    push = open_socket(zctx, SocketSpec(zmq.PUSH, ep))
    try:
        push.send(b"x" * (transport.SMALL_MAX_MSG_BYTES + 1))
        assert not pull.poll(500)
        push2 = open_socket(zctx, SocketSpec(zmq.PUSH, ep))  # the socket itself lives on
        push2.send(b"ok")
        assert pull.poll(2000) and pull.recv() == b"ok"
        push2.close(linger=0)
    finally:
        pull.close(linger=0)
        push.close(linger=0)


def _tap(zctx, path: Path) -> tuple[zmq.Socket[bytes], TapGate, str]:
    ep = f"ipc://{path}"
    sock = open_socket(zctx, SocketSpec(zmq.XPUB, ep, bind=True, rcvhwm=tap_gate.TAP_RCVHWM,
                                        xpub_manual=True))
    return sock, TapGate(sock, (b"meta", b"stats")), ep


def test_gate_takes_only_prefixes_of_its_topics(zctx, tmp_path: Path) -> None:
    sock, gate, ep = _tap(zctx, tmp_path / "tap")
    sub = zctx.socket(zmq.SUB)
    try:
        sub.connect(ep)
        for topic in (b"meta", b"st", b"bogus", b"metaX", b"\x00\xff"):
            sub.setsockopt(zmq.SUBSCRIBE, topic)
        poll_for(lambda: gate.drain() or gate.refused >= 3, 5, what="subscriptions read")
        poll_for(lambda: (gate.drain(), gate.refused == 3 and len(gate.readers) == 2)[1], 5,
                 what="two readers, three refused")
        assert gate.readers == {b"meta": 1, b"st": 1}
        assert gate.wanted(b"meta") and gate.wanted(b"stats") and not gate.wanted(b"image")
        time.sleep(0.1)
        sock.send_multipart([b"stats", b"1"])
        assert sub.poll(2000) and sub.recv_multipart() == [b"stats", b"1"]
        sub.setsockopt(zmq.UNSUBSCRIBE, b"st")
        poll_for(lambda: (gate.drain(), not gate.wanted(b"stats"))[1], 5, what="unsubscribed")
    finally:
        sub.close(linger=0)
        sock.close(linger=0)


def test_huge_subscription_costs_only_its_sender_the_connection(zctx, tmp_path: Path) -> None:
    sock, gate, ep = _tap(zctx, tmp_path / "tap")
    reader, hostile = zctx.socket(zmq.SUB), zctx.socket(zmq.SUB)
    try:
        reader.connect(ep)
        reader.setsockopt(zmq.SUBSCRIBE, b"meta")
        hostile.connect(ep)
        hostile.setsockopt(zmq.SUBSCRIBE, b"m" * (64 << 10))  # would match "meta..." if kept
        poll_for(lambda: (gate.drain(), gate.wanted(b"meta"))[1], 5, what="reader subscribed")
        time.sleep(0.3)
        gate.drain()
        assert gate.readers == {b"meta": 1} and gate.refused == 0  # never reached the process
        sock.send_multipart([b"meta", b"m"])
        assert reader.poll(2000) and reader.recv_multipart() == [b"meta", b"m"]
        assert not hostile.poll(300)
    finally:
        reader.close(linger=0)
        hostile.close(linger=0)
        sock.close(linger=0)
