"""The supervisor's orders to the broker: their own channel (an ipc file in the 0700 run
directory), every order sealed with the run's key handed to the broker at spawn. What does
not open with that key is refused whole (issue 26 item 9: an identity string on the
workers' socket let any process of the same user pose as the supervisor)."""

from __future__ import annotations

from collections.abc import Callable, Iterator

import zmq

from trapflow.errors import ProtocolError
from trapflow.wire import control_msgs
from trapflow.wire.links import Poller
from trapflow.wire.transport import SocketSpec, open_socket, zmq_readable

BATCH = 64  # orders read per wake-up at most: the pairs' path is never starved


class OrdersChannel:
    """The broker's end: a PULL it binds, read in batches, each order's seal checked."""

    def __init__(self, ctx: zmq.Context[zmq.Socket[bytes]], endpoint: str, key: bytes,
                 poller: Poller) -> None:
        self.sock = open_socket(ctx, SocketSpec(zmq.PULL, endpoint, bind=True, rcvhwm=100))
        self.key = key
        self.poller = poller
        poller.register(self.sock)

    def drain(self, refuse: Callable[[str], None]) -> Iterator[control_msgs.SupervisorOrder]:
        """The orders waiting now, opened; refuse(why) for each that does not open."""
        self.poller.touch(self.sock)
        for _ in range(BATCH):
            if not zmq_readable(self.sock):
                return
            frames = self.sock.recv_multipart(copy=False)
            try:
                yield control_msgs.open_order(self.key, frames)
            except ProtocolError as exc:  # not the supervisor's: nothing of it is applied
                refuse(str(exc))
