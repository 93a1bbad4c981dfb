"""The event-capture process: keeps the pairs around a trigger in an event folder.

Owns a SUB connected to the broker's tap (images) and the normalizer's tap
(results). Like any tap it never slows the pipeline: a busy disk loses tap
messages here, not pairs upstream.
"""

from __future__ import annotations

import logging

import zmq

from trapflow.errors import ProtocolError
from trapflow.events.clips import EventCapture
from trapflow.runtime.node import ACTIVE, FINALIZED, Node, NodeSpec
from trapflow.runtime.ratelog import RateLimitedLog
from trapflow.wire import jpeg, tap_msgs
from trapflow.wire.transport import SocketSpec, open_socket

log = logging.getLogger(__name__)


class EventsNode(Node):
    """Feeds tap images and results to EventCapture."""

    def __init__(self, spec: NodeSpec) -> None:
        super().__init__(spec)
        self.sub = open_socket(self.ctx, SocketSpec(
            zmq.SUB, self.endpoints.tap, subscribe=(tap_msgs.TOPIC_IMAGE, tap_msgs.TOPIC_RESULT),
            rcvhwm=64))
        self.sub.connect(self.endpoints.results_tap)
        self.capture = EventCapture(self.cfg.events, spec.run_dir / self.cfg.events.folder)
        self.malformed = 0
        self.ratelog = RateLimitedLog(log)

    def counters(self) -> dict[str, int]:
        return {"malformed": self.malformed}

    def run(self) -> int:
        self.set_state(ACTIVE)
        while not self.stopping:
            if self.sub.poll(100, zmq.POLLIN):
                frames = self.sub.recv_multipart(copy=False)
                try:
                    self._handle(frames)
                except (ProtocolError, ValueError) as exc:
                    self.malformed += 1
                    self.ratelog.warning("events", "skipped tap message: %s", exc)
            self.beat()
        self.capture.close()
        self.set_state(FINALIZED)
        return 0

    def _handle(self, frames: list[zmq.Frame]) -> None:
        msg = tap_msgs.decode_tap(frames)
        if isinstance(msg, tap_msgs.TapPair):
            # Raw pairs (the default ring) become JPEG here, once: the pre-roll holds
            # hundreds of pairs and an event folder keeps photos, not 2.7 MB frames.
            header, left, right = jpeg.to_jpeg_pair(msg.header, msg.left, msg.right,
                                                    self.cfg.source.jpeg_quality)
            self.capture.on_pair(header, left, right)
        elif isinstance(msg, tap_msgs.TapResult):
            self.capture.on_result({msg.kind: msg.fields})
