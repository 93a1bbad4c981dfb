"""The viewer as a pipeline node (`trapflow start --view`): the web server in its own process.

Owns, besides its heartbeat PUSH, the viewer's tap SUB and control REQ (trapflow.viewer.taps)
and the HTTP port. Active once the port is bound; a port already taken is a start-up
failure with the reason, not a crash loop.
"""

from __future__ import annotations

import asyncio
import logging
import time

from trapflow.errors import ConfigError
from trapflow.runtime.node import ACTIVE, FINALIZED, INACTIVE, Node, NodeSpec
from trapflow.viewer.server import serve

log = logging.getLogger(__name__)


class ViewerNode(Node):
    """Serves the page until the supervisor asks it to stop."""

    def __init__(self, spec: NodeSpec) -> None:
        super().__init__(spec)
        self.url = ""

    def _ready(self, url: str) -> None:
        self.url = url
        # The address rides on the state to the supervisor, which prints it (`--view`).
        self.set_state(ACTIVE, url, normal=True)
        self.beat()

    def run(self) -> int:
        v = self.cfg.viewer
        try:
            asyncio.run(serve(self.cfg, self.spec.run_dir, v.host, v.port, self.spec.viewer_token,
                              ready=self._ready,
                              beat=self.beat, stopping=lambda: self.stopping))
        except (OSError, ConfigError) as exc:
            why = (str(exc) if isinstance(exc, ConfigError) else
                   f"cannot serve on {v.host}:{v.port}: {exc.strerror or exc}; "
                   "choose another port with --view [HOST:]PORT")
            self.set_state(INACTIVE, why)
            self.beat()
            while not self.stopping:  # the supervisor reports the reason and stops the run
                time.sleep(0.1)
                self.beat()
            return 1
        self.set_state(FINALIZED)
        return 0
