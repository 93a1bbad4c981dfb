"""Signed operator commands over the modem link: the key, the tag, the counter rules.

CommandGuard is the box's pure decision core (no port, no sockets, no clock: `now` is
passed in). It takes COMMAND payloads and answers what to do: execute, send the cached
reply again, tell the surface it is busy or out of date, or refuse in silence. Its state
(the highest accepted counter, that command's tag and reply) is saved by the shell before
a command runs (trapflow.modem.node), so a power cut never lets a command run twice.
Also here: the key file, the counter file's durable write, the mapping of a command to
its control request, and the surface's grammar (`trapflow surface --command`).
"""

from __future__ import annotations

import hmac
import os
import shlex
import stat
from collections import OrderedDict
from dataclasses import dataclass, field
from hashlib import sha256
from pathlib import Path
from typing import Any

import msgspec

from trapflow.config.modem import MAX_PAYLOAD
from trapflow.errors import ConfigError, ProtocolError
from trapflow.modem.codec import LinkCodec
from trapflow.modem.frame import (
    CMD_HEALTH,
    CMD_KINDS,
    CMD_LEVEL,
    CMD_PARAM,
    CMD_POOL_ACTIVATE,
    CMD_POOL_COUNT,
    CMD_POOL_DEACTIVATE,
    CMD_POOL_POLICY,
    CMD_STATUS,
    COMMAND,
    REPLY,
    REPLY_BUSY,
    REPLY_ERROR,
    REPLY_LOST,
    REPLY_SESSION,
    REPLY_STALE,
    SESSION_BYTES,
    TAG_BYTES,
    Command,
    SignedFrame,
    parse_command_body,
    signed_payload,
    split_signed,
)
from trapflow.runtime.files import write_atomically
from trapflow.wire import control_msgs, messages

MIN_KEY_BYTES = 16
REFUSAL_REPLY_INTERVAL_S = 5.0
"""At most one stale or wrong-session reply per frame per this interval: each costs link
time, and a replayed frame must not be able to spend the box's budget. Per frame, not one
slot for all: an old frame replayed once a second took the only slot, so the surface's own
command to the wrong session never heard its correction (issue 26 item 7)."""
MAX_ANSWERED_FRAMES = 1024
"""Frames whose refusal was answered, remembered (oldest forgotten first): a frame not among
them is answered at once and not as a repeat, so only genuine frames recorded by the
thousand could spend the repeats' share of the budget."""
REPEAT_REPLY_INTERVAL_S = 5.0
"""At most one cached (or "reply lost") answer per this interval for the last command: a
recorded frame replayed 3 times a second once drained the hourly budget in 30 s (issue 26).
The surface retries after 8 s at the soonest, so each of its retransmissions is answered."""
MAX_REPEAT_INTERVAL_S, REPEAT_BACKOFF = 60.0, 1.5
"""The wait between two answers to one frame heard again grows 1.5 times an answer, to a
minute: a replay once a second is answered at 0, 5, 12.5, 23.8 s... (issue 36 item 2). It
is the surface's own back-off (8 s times 1.5 to 60 s) from a shorter start, so each of the
surface's retransmissions is still answered."""
MAX_REPLY_BODY = MAX_PAYLOAD - SESSION_BYTES - 5 - TAG_BYTES  # a counter takes at most 5


# --- the key ---------------------------------------------------------------------------


def load_key(path: str | Path) -> bytes:
    """The shared key from its file: readable by its owner only, at least 16 bytes."""
    path = Path(path)
    try:
        st = os.stat(path)
    except OSError as exc:
        raise ConfigError(
            f"command key file {path}: expected a readable file, got "
            f"{exc.strerror}; make one with `head -c 32 /dev/urandom > {path}; "
            f"chmod 600 {path}`"
        ) from None
    if st.st_mode & 0o077:
        raise ConfigError(
            f"command key file {path} is readable by group or others (mode "
            f"{stat.S_IMODE(st.st_mode):03o}): expected mode 600; fix it with "
            f"`chmod 600 {path}`"
        )
    key = path.read_bytes()
    if len(key) < MIN_KEY_BYTES:
        raise ConfigError(
            f"command key file {path}: expected at least {MIN_KEY_BYTES} bytes, "
            f"got {len(key)}; make one with `head -c 32 /dev/urandom > {path}`"
        )
    return key


def tag(key: bytes, signed: bytes) -> bytes:
    """The truncated HMAC-SHA256 of the signed bytes (frame type, session, counter, body)."""
    return hmac.new(key, signed, sha256).digest()[:TAG_BYTES]


def sign(key: bytes, kind: int, session: bytes, counter: int, body: bytes) -> bytes:
    """A COMMAND or REPLY payload with its tag."""
    head = signed_payload(session, counter, body)
    return head + tag(key, bytes((kind,)) + head)


def verify(key: bytes, frame: SignedFrame) -> bool:
    """Whether the frame's tag is the key's (compared in constant time)."""
    return hmac.compare_digest(frame.tag, tag(key, frame.signed))


def write_durably(path: Path, data: bytes) -> None:
    """Replace path with data atomically and durably, readable by its owner only."""
    write_atomically(path, data, mode=0o600)


# --- the box's memory of commands ----------------------------------------------------------


class CounterState(msgspec.Struct, kw_only=True, forbid_unknown_fields=True):
    """The last accepted command of one outbox session (the file beside the outbox)."""

    version: int = 1
    session: str = ""  # hex; another session's counter does not apply (new outbox)
    counter: int = 0  # the highest accepted counter
    tag: str = ""  # hex tag of that command: a retransmission carries the same
    reply: str = ""  # hex reply payload sent for it ("" until it has run)
    # The supervisor run it was taken in: runtime changes (pool counts, levels, parameters)
    # live only as long as that run, so after a restart its cached "ok" no longer holds.
    run: str = ""


def load_counter(path: Path, session: bytes) -> CounterState:
    """The saved state for this session; a fresh one when there is none. A corrupt file is
    an error: starting from 0 would let every old command run again."""
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        return CounterState(session=session.hex())
    try:
        state = msgspec.json.decode(data, type=CounterState)
    except msgspec.DecodeError as exc:
        raise ConfigError(
            f"command counter file {path} is corrupt ({exc}): expected the "
            f"JSON it was saved as; remove it only with a fresh outbox (a new "
            f"session), or old commands could be replayed"
        ) from None
    if state.session != session.hex():
        return CounterState(session=session.hex())
    return state


def save_counter(path: Path, state: CounterState) -> None:
    """Write the state durably (before the command it names is executed)."""
    write_durably(path, msgspec.json.encode(state) + b"\n")


# --- decisions ---------------------------------------------------------------------------


@dataclass(frozen=True)
class Execute:
    """Run the command; save the state first (the counter is taken)."""

    counter: int
    command: Command
    state: CounterState


@dataclass(frozen=True)
class Reply:
    """Send this REPLY payload (a cached reply, or a refusal the surface must hear).
    `repeat`: a frame heard before can ask for it again (cached, lost, stale, session), so
    the sender gives it only a share of the hourly budget."""

    payload: bytes
    repeat: bool = False


@dataclass(frozen=True)
class Refuse:
    """Drop the frame; `why` is logged (rate-limited), `kind` counted."""

    kind: str
    why: str


Decision = Execute | Reply | Refuse


@dataclass
class CommandGuard:
    """The counter and tag rules of the box. receive() decides; finished() makes the reply."""

    key: bytes | None  # None: no key configured, every command is refused
    session: bytes
    state: CounterState
    run: str = ""  # this start of the box (trapflow.runtime.node.NodeSpec.run_id)
    running: int | None = None  # counter of the command being executed
    disabled: str = ""  # why every command is refused (the counter file cannot be trusted)
    counts: dict[str, int] = field(default_factory=dict)
    # tag of a frame whose refusal was answered -> (when it may be answered again, the wait
    # after that answer)
    _answered: OrderedDict[bytes, tuple[float, float]] = field(default_factory=OrderedDict)
    # (counter, when it may be answered again, the wait after that answer)
    _next_repeat_reply: tuple[int, float, float] = (0, 0.0, REPEAT_REPLY_INTERVAL_S)

    def _count(self, kind: str) -> None:
        self.counts[kind] = self.counts.get(kind, 0) + 1

    def _refuse(self, kind: str, why: str) -> Refuse:
        self._count(kind)
        return Refuse(kind, why)

    def _refusal_reply(
        self, kind: str, status: int, frame: SignedFrame, data: dict[str, Any], now: float
    ) -> Decision:
        """A stale or wrong-session frame's answer: a frame heard for the first time is
        answered at once (the surface's own, to be corrected); the same frame again at most
        once per REFUSAL_REPLY_INTERVAL_S, the interval doubling at each answer up to
        MAX_REPEAT_INTERVAL_S, as a repeat (a replay, or a retransmission)."""
        self._count(kind)
        held = self._answered.get(frame.tag)
        if held is not None and now < held[0]:
            self._count("replies_held")
            return Refuse(kind, f"{kind} (reply held back: the same frame is answered "
                                f"again in {held[0] - now:.1f} s, backing off)")
        wait = REFUSAL_REPLY_INTERVAL_S if held is None else held[1]
        self._answered[frame.tag] = (now + wait, min(wait * REPEAT_BACKOFF,
                                                     MAX_REPEAT_INTERVAL_S))
        self._answered.move_to_end(frame.tag)
        while len(self._answered) > MAX_ANSWERED_FRAMES:
            self._answered.popitem(last=False)
        return Reply(self.reply(frame.counter, status, data), repeat=held is not None)

    def _repeat_reply(self, counter: int, now: float) -> Decision:
        """The last command's answer again (its cached reply, or that it was lost), at most
        once per REPEAT_REPLY_INTERVAL_S for that counter, the interval doubling at each
        answer up to MAX_REPEAT_INTERVAL_S."""
        self._count("duplicates")
        held_counter, next_at, wait = self._next_repeat_reply
        if held_counter == counter and now < next_at:
            self._count("replies_held")
            return Refuse(
                "duplicates",
                f"command {counter} again (answered at most once per {wait:g} s, backing "
                f"off to {MAX_REPEAT_INTERVAL_S:g} s)",
            )
        if held_counter != counter:
            wait = REPEAT_REPLY_INTERVAL_S
        longer = min(wait * REPEAT_BACKOFF, MAX_REPEAT_INTERVAL_S)
        self._next_repeat_reply = (counter, now + wait, longer)
        if self.state.reply and self.state.run == self.run:
            return Reply(bytes.fromhex(self.state.reply), repeat=True)
        if self.state.run != self.run:
            # Taken in an earlier start of the box (a power cut): whatever it changed was
            # runtime state, gone with that start, so its cached "ok" would now be false
            # (issue 26). It never runs twice: the surface sends it again to apply it.
            why = (f"command {counter} ran before the box restarted: what it changed no "
                   "longer applies (runtime changes end with a restart); send it again")
        else:
            # Taken before the modem node restarted in this run, its reply unsaved.
            why = f"command {counter} was taken before the box restarted; its reply is lost"
        return Reply(self.reply(counter, REPLY_LOST, {"error": why}), repeat=True)

    def reply(self, counter: int, status: int, data: dict[str, Any]) -> bytes:
        """A signed REPLY payload for this counter."""
        assert self.key is not None
        return sign(self.key, REPLY, self.session, counter, reply_body(status, data))

    def receive(self, payload: bytes, now: float) -> Decision:
        """What to do with one COMMAND payload."""
        # Long on purpose: the checks of one received command in the order that makes a
        # replay or forgery harmless (frame, signature, counter, state saved, then run);
        # split, a later check could run before an earlier one.
        if self.key is None:
            return self._refuse(
                "refused_no_key",
                "command received but modem.command_key "
                "is not set: expected a key file shared with the surface",
            )
        if self.disabled:
            return self._refuse("refused_disabled", self.disabled)
        try:
            frame = split_signed(COMMAND, payload)
        except ProtocolError as exc:
            return self._refuse("refused_malformed", f"malformed command: {exc}")
        if not verify(self.key, frame):
            return self._refuse(
                "refused_tag",
                f"command {frame.counter} with a bad tag "
                "(forged, damaged, or signed with another key)",
            )
        if frame.session != self.session:
            return self._refusal_reply(
                "refused_session",
                REPLY_SESSION,
                frame,
                {
                    "error": f"addressed to session {frame.session.hex()}, this box's is "
                    f"{self.session.hex()}"
                },
                now,
            )
        last = self.state.counter
        if frame.counter == last and frame.tag.hex() == self.state.tag:
            if self.running == frame.counter:
                return self._refuse("duplicates", f"command {last} again while it runs")
            return self._repeat_reply(last, now)
        if frame.counter <= last:
            return self._refusal_reply(
                "refused_old",
                REPLY_STALE,
                frame,
                {
                    "error": f"counter {frame.counter} is not above the last accepted {last}",
                    "last": last,
                },
                now,
            )
        if self.running is not None:
            self._count("busy")
            return Reply(
                self.reply(
                    frame.counter, REPLY_BUSY, {"error": f"command {self.running} still runs"}
                )
            )
        try:
            cmd = parse_command_body(frame.body)
        except (ProtocolError, IndexError) as exc:
            # Authentic but not understood (a newer surface): the counter is taken, the
            # reply says why, and a retransmission gets that reply.
            cmd = Command(0, text=str(exc))
        self.state = CounterState(
            session=self.session.hex(), counter=frame.counter, tag=frame.tag.hex(), run=self.run
        )
        self.running = frame.counter
        self._count("accepted")
        return Execute(frame.counter, cmd, self.state)

    def finished(
        self, counter: int, status: int, data: dict[str, Any]
    ) -> tuple[bytes, CounterState]:
        """The command ran: its reply, cached for retransmissions, and the state to save."""
        payload = self.reply(counter, status, data)
        if counter == self.state.counter:
            self.state = msgspec.structs.replace(self.state, reply=payload.hex())
        if self.running == counter:
            self.running = None
        self._count("executed" if status != REPLY_ERROR else "failed")
        return payload, self.state


# --- reply bodies ----------------------------------------------------------------------------

_CODEC = LinkCodec()  # replies use the default label table (the health record's has none)


def reply_body(status: int, data: dict[str, Any]) -> bytes:
    """Status byte, then the data as a link record (a health record rides compact), cut to
    fit one frame: long text is shortened, then the largest entries dropped."""
    codec = _CODEC
    data = dict(data)
    while True:
        body = bytes((status,)) + codec.encode(data)
        if len(body) <= MAX_REPLY_BODY:
            return body
        texts = [k for k, v in data.items() if isinstance(v, str) and len(v) > 43]
        if texts:
            k = texts[0]
            data[k] = data[k][: max(40, len(data[k]) - (len(body) - MAX_REPLY_BODY) - 3)] + "..."
            continue
        if not data:
            return bytes((status,)) + codec.encode({"error": "reply too large"})
        biggest = max(data, key=lambda k: len(msgspec.msgpack.encode(data[k])))
        del data[biggest]
        data["cut"] = True


def parse_reply_body(body: bytes) -> tuple[int, dict[str, Any]]:
    """Inverse of reply_body: (status, data); ProtocolError when malformed."""
    return body[0], _CODEC.decode(body[1:])


def control_request(cmd: Command) -> messages.Msg | None:
    """The supervisor request that executes a command (None: the modem answers it)."""
    if cmd.kind == CMD_LEVEL:
        return control_msgs.LevelRequest(level=cmd.text)
    if cmd.kind == CMD_POOL_COUNT:
        return control_msgs.PoolRequest(pool=cmd.pool, count=cmd.count)
    if cmd.kind in (CMD_POOL_ACTIVATE, CMD_POOL_DEACTIVATE):
        return control_msgs.PoolRequest(pool=cmd.pool, active=cmd.kind == CMD_POOL_ACTIVATE)
    if cmd.kind == CMD_POOL_POLICY:
        return control_msgs.PoolRequest(pool=cmd.pool, policy=cmd.text)
    if cmd.kind == CMD_PARAM:
        return control_msgs.ParamRequest(pool=cmd.pool, key=cmd.text, value=cmd.value)
    if cmd.kind == CMD_STATUS:
        return control_msgs.StatusRequest()
    return None


def status_summary(st: dict[str, Any]) -> dict[str, Any]:
    """The few numbers of `trapflow status` that fit a reply: uptime, nodes active,
    pairs in, and per pool [state, workers, processed, dropped, rate]."""
    nodes = st.get("nodes") or []
    active = sum(1 for n in nodes if n.get("state") == "active")
    stats = st.get("stats") or {}
    sup = st.get("supervision") or {}
    pools: dict[str, list[Any]] = {}
    for name, p in (stats.get("pools") or {}).items():
        ctl = (sup.get("pools") or {}).get(name, {})
        pools[name] = [
            ctl.get("state", "active" if p.get("active", True) else "inactive"),
            p.get("workers", 0),
            p.get("processed", 0),
            p.get("dropped", 0),
            p.get("rate", 0.0),
        ]
    return {
        "status": {
            "uptime_s": int(st.get("uptime_s", 0)),
            "active": f"{active}/{len(nodes)}",
            "pairs_in": stats.get("pairs_in", 0),
            "changes": sup.get("control", 0),
            "gave_up": sup.get("gave_up", 0),
            **({"level": sup["ladder"]["level"]} if sup.get("ladder") else {}),
        },
        "pools": pools,
    }


# --- the surface's grammar ----------------------------------------------------------------


def parse_command_text(text: str) -> Command:
    """One command of `trapflow surface --command` (its --help lists them); ValueError
    saying what was expected and what came."""
    try:
        words = shlex.split(text)
    except ValueError as exc:
        raise ValueError(
            f"expected a command like 'pool stereo --count 2', got {text!r}: {exc}"
        ) from None
    if not words:
        raise ValueError("expected a command (level, pool, param, status, health), got none")
    verb, args = words[0], words[1:]

    def want(n: int, usage: str) -> None:
        if len(args) != n:
            raise ValueError(f"expected `{usage}`, got {text!r}")

    if verb in ("status", "health"):
        want(0, verb)
        return Command(CMD_STATUS if verb == "status" else CMD_HEALTH)
    if verb == "level":
        want(1, "level NAME|auto")
        return Command(CMD_LEVEL, text=args[0])
    if verb == "param":
        want(2, "param POOL KEY=VALUE")
        from trapflow.wire.control_client import parse_assignment

        key, value = parse_assignment(args[1])
        return Command(CMD_PARAM, args[0], text=key, value=value)
    if verb == "pool":
        usage = "pool NAME --count N|--activate|--deactivate|--policy P"
        if len(args) == 2 and args[1] in ("--activate", "--deactivate"):
            return Command(
                CMD_POOL_ACTIVATE if args[1] == "--activate" else CMD_POOL_DEACTIVATE, args[0]
            )
        want(3, usage)
        if args[1] == "--count":
            if not args[2].isdigit():
                raise ValueError(f"pool {args[0]} --count: expected a number, got {args[2]!r}")
            return Command(CMD_POOL_COUNT, args[0], count=int(args[2]))
        if args[1] == "--policy":
            return Command(CMD_POOL_POLICY, args[0], text=args[2])
        raise ValueError(f"expected `{usage}`, got {text!r}")
    raise ValueError(f"expected a command of: level, pool, param, status, health; got {verb!r}")


def describe(cmd: Command) -> str:
    """A command in the grammar's words (for logs)."""
    name = CMD_KINDS.get(cmd.kind, f"kind {cmd.kind}")
    parts = [name, cmd.pool, cmd.text if cmd.kind != CMD_PARAM else f"{cmd.text}={cmd.value!r}"]
    if cmd.kind == CMD_POOL_COUNT:
        parts.append(str(cmd.count))
    return " ".join(p for p in parts if p)
