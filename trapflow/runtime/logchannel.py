"""Log records from every node to one listener in the supervisor, over ZeroMQ.

Owns two sockets: each node's PUSH (LogSender) and the supervisor's PULL (LogListener, in
its own thread with its own socket), bound at the run directory's log.sock. Records travel
as control_msgs.LogEntry structs, never pickled. Unlike multiprocessing's queue this creates
no named semaphore in /dev/shm, so a kill -9 of the whole process group leaves nothing.
"""

from __future__ import annotations

import io
import logging
import logging.handlers
import os
import threading

import zmq

from trapflow.errors import ProtocolError
from trapflow.runtime.ratelog import CONSOLE_ONCE, RateLimitedLog, wire
from trapflow.wire import control_msgs, messages
from trapflow.wire.endpoints import set_file_mode
from trapflow.wire.transport import SocketSpec, new_context, open_socket

log = logging.getLogger(__name__)

# Records a node queues while the listener is slow; past this, records are dropped rather
# than blocking the node's loop (a flood of warnings must not stall the pipeline).
SEND_HWM = 10_000
_POLL_MS = 100  # how often the listener thread checks whether it should stop


class PrivateRotatingFile(logging.handlers.RotatingFileHandler):
    """The run's log file, 0640 whatever the umask: each new file after a rotation too."""

    def _open(self) -> io.TextIOWrapper:
        stream = super()._open()
        set_file_mode(self.baseFilename)
        return stream


class LogSender(logging.Handler):
    """A node's handler: format each record and push it, never blocking the node."""

    def __init__(self, endpoint: str, process: str) -> None:
        super().__init__()
        self.process = process
        self.dropped = 0
        self._ctx = new_context()  # its own: node contexts are destroyed before the last log
        self._sock = open_socket(self._ctx, SocketSpec(zmq.PUSH, endpoint, sndhwm=SEND_HWM))
        self._lock_send = threading.Lock()  # a handler may be called from several threads

    def emit(self, record: logging.LogRecord) -> None:
        try:
            text = self.format(record) if self.formatter else record.getMessage()
            if record.exc_info and not self.formatter:
                text += "\n" + logging.Formatter().formatException(record.exc_info)
            text = text[: messages.MAX_LOG_BYTES // 2]  # leaves room for the other fields
            entry = control_msgs.LogEntry(name=record.name, levelno=record.levelno,
                                      process=self.process, pid=os.getpid(),
                                      created=record.created, message=text,
                                      console_once=bool(getattr(record, CONSOLE_ONCE, False)))
            with self._lock_send:
                self._sock.send(messages.encode(entry), zmq.NOBLOCK)
        except zmq.Again:
            self.dropped += 1
        except Exception:  # noqa: BLE001 - a log handler reports through handleError
            self.handleError(record)

    def close(self) -> None:
        with self._lock_send:
            self._sock.close(linger=500)  # give the last records (a traceback) a moment
            self._ctx.term()
        super().close()


class LogListener:
    """The supervisor's end: a thread that takes LogEntry records and hands them to handlers.

    A record that does not decode is counted and warned about at most once per interval.
    """

    def __init__(self, ctx: zmq.Context[zmq.Socket[bytes]], endpoint: str,
                 handlers: list[logging.Handler]) -> None:
        self.handlers = handlers
        self.malformed = 0
        self._sock = open_socket(ctx, SocketSpec(zmq.PULL, endpoint, bind=True,
                                                 rcvhwm=SEND_HWM))
        self._stop = threading.Event()
        self._ratelog = RateLimitedLog(log)
        self._thread = threading.Thread(target=self._loop, name="log-listener", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def handle(self, record: logging.LogRecord) -> None:
        """Pass one record (a node's or the supervisor's own) to every handler."""
        for h in self.handlers:
            if record.levelno >= h.level:
                h.handle(record)

    def _take(self, data: bytes) -> None:
        try:
            e = control_msgs.decode_log(data)
        except ProtocolError as exc:
            self.malformed += 1
            self._ratelog.warning("log", "dropped malformed log record: %s", wire(str(exc)))
            return
        record = logging.makeLogRecord({
            "name": e.name, "levelno": e.levelno, "levelname": logging.getLevelName(e.levelno),
            "processName": e.process, "process": e.pid, "created": e.created,
            "msecs": (e.created % 1) * 1000,
            "msg": e.message, "args": None, CONSOLE_ONCE: e.console_once,
        })
        self.handle(record)

    def _loop(self) -> None:
        while not self._stop.is_set():
            if self._sock.poll(_POLL_MS, zmq.POLLIN):
                self._drain()
        self._drain()

    def _drain(self) -> None:
        while True:
            try:
                data = self._sock.recv(zmq.NOBLOCK)
            except zmq.Again:
                return
            self._take(data)

    def stop(self) -> None:
        """Take what is waiting, stop the thread and close the socket."""
        self._stop.set()
        self._thread.join(5.0)
        self._sock.close(linger=0)
