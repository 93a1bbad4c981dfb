"""The broker's local links: who is connected over the run directory's seqpacket sockets.

One listener per role (capture, worker, results), one Link per connected peer, found by its
file descriptor (what the poller reports), its role, and for a worker the name it gave in
its first message; the normalizer's one link; and the capture links held back from the
poller while a pool is full. The broker decides what each message means; this registry only
keeps the tables consistent (a link is in all of them or in none) and the poller with them.
"""

from __future__ import annotations

import contextlib
import os
import socket
from collections.abc import Iterable
from dataclasses import dataclass

from trapflow.wire.links import Link, Poller, accept_link, listen_link


@dataclass(frozen=True)
class Removed:
    """What a removed link was: a worker's (its name, when this link held it) or the
    normalizer's."""

    ident: bytes | None
    was_results: bool


class LinkRegistry:
    """Listeners and connected links by file descriptor, role and worker name."""

    def __init__(self, poller: Poller) -> None:
        self.poller = poller
        self.listeners: dict[socket.socket, str] = {}
        self._by_fd: dict[int, socket.socket | Link] = {}
        self._roles: dict[Link, str] = {}
        self._idents: dict[Link, bytes] = {}
        self._workers: dict[bytes, Link] = {}
        self._held: set[Link] = set()  # capture links not polled (the broker's pacing)
        self.results_link: Link | None = None  # the normalizer, once it connected

    # --- listeners ----------------------------------------------------------------------

    def listen(self, path: str, role: str) -> None:
        """Listen for peers of `role` at `path` (polled from now on)."""
        listener = listen_link(path)
        self.listeners[listener] = role
        self.poller.register(listener)
        self._by_fd[listener.fileno()] = listener

    def listener_of(self, role: str) -> socket.socket:
        """The listener of a role (KeyError if the broker does not listen for it)."""
        return next(lst for lst, r in self.listeners.items() if r == role)

    def ready(self, fds: Iterable[int]) -> list[socket.socket | Link]:
        """The listeners and links behind the descriptors the poller reported, in order."""
        return [self._by_fd[fd] for fd in fds if fd in self._by_fd]

    def pending(self, listener: socket.socket) -> list[Link]:
        """Every connection waiting on a listener, accepted (not registered yet)."""
        out = []
        while (link := accept_link(listener)) is not None:
            out.append(link)
        return out

    # --- links --------------------------------------------------------------------------

    def add(self, link: Link, role: str) -> None:
        """A connected peer of `role`, polled from now on; a results link becomes the
        normalizer's."""
        if role == "results":
            self.results_link = link
        self._roles[link] = role
        self._by_fd[link.fileno()] = link
        self.poller.register(link)

    def role(self, link: Link) -> str | None:
        """The role a link connected for, or None once it is removed."""
        return self._roles.get(link)

    def links(self, role: str | None = None) -> list[Link]:
        """The connected links (of one role)."""
        return [link for link, r in self._roles.items() if role is None or r == role]

    def ident(self, link: Link) -> bytes | None:
        """The name a worker link gave, or None before its first message."""
        return self._idents.get(link)

    def name(self, link: Link, ident: bytes) -> bool:
        """Give a worker link its name; False (nothing changed) when a live link has it."""
        if ident in self._workers:
            return False
        self._idents[link] = ident
        self._workers[ident] = link
        return True

    def worker(self, ident: bytes) -> Link | None:
        """The local link of a named worker, or None (a remote worker, or gone)."""
        return self._workers.get(ident)

    def hold(self, link: Link) -> bool:
        """Stop polling a link (what it sends waits in it); False if held already."""
        if link in self._held:
            return False
        self.poller.unregister(link)
        self._held.add(link)
        return True

    def release(self, link: Link) -> bool:
        """Poll a held link again; False if it was not held."""
        if link not in self._held:
            return False
        self._held.discard(link)
        self.poller.register(link)
        return True

    def remove(self, link: Link) -> Removed | None:
        """Forget a link and close it: what it was, or None if it was not registered (removed
        earlier in this pass)."""
        if link not in self._roles:
            return None
        if link not in self._held:  # a held link is not polled
            self.poller.unregister(link)
        self._held.discard(link)
        self._by_fd.pop(link.fileno(), None)
        del self._roles[link]
        ident = self._idents.pop(link, None)
        was_results = link is self.results_link
        if was_results:
            self.results_link = None
        link.close()
        if ident is not None and self._workers.get(ident) is link:
            del self._workers[ident]
            return Removed(ident, was_results)
        return Removed(None, was_results)

    def close(self) -> None:
        """Close every link and listener; a listener's socket file is removed (a successor
        binds afresh; a finished run leaves no socket)."""
        for link in list(self._roles):
            link.close()
        for listener in self.listeners:
            path = listener.getsockname()
            listener.close()
            with contextlib.suppress(OSError):
                os.unlink(path)
        # Closed once: a second close (the node's, after its loop's) finds nothing to do.
        self.listeners.clear()
        self._roles.clear()
        self._by_fd.clear()
        self._idents.clear()
        self._workers.clear()
        self._held.clear()
        self.results_link = None
