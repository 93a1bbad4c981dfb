"""Signed surface commands: the COMMAND/REPLY codec, the HMAC tag, the box's counter rules
(trapflow.modem.command.CommandGuard, no port, no clock), the key file, the counter
files, the surface's grammar and its client's corrections."""

from __future__ import annotations

import time
from pathlib import Path

import pytest
import zmq

from tests.conftest import poll_for, recv
from trapflow.config.modem import MAX_PAYLOAD
from trapflow.errors import ConfigError, ProtocolError
from trapflow.modem import command as C  # noqa: N812 - short: named on most lines
from trapflow.modem.frame import (
    CMD_HEALTH,
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
    REPLY_OK,
    REPLY_SESSION,
    REPLY_STALE,
    TAG_BYTES,
    Command,
    Deframer,
    command_body,
    frame,
    parse_command_body,
    split_signed,
)
from trapflow.modem.surface_command import CommandClient, take_counter
from trapflow.wire import control_msgs, messages
from trapflow.wire.control_client import ControlClient
from trapflow.wire.transport import SocketSpec, open_socket

KEY = bytes(range(32))
OTHER_KEY = bytes(range(1, 33))
SESSION = bytes.fromhex("8c41d20e")


def cmd_payload(counter: int, cmd: Command | None = None, key: bytes = KEY,
                session: bytes = SESSION, body: bytes | None = None) -> bytes:
    body = command_body(cmd or Command(CMD_POOL_COUNT, "stereo", count=2)) if body is None \
        else body
    return C.sign(key, COMMAND, session, counter, body)


def reply_of(payload: bytes) -> tuple[int, int, dict]:
    """(counter, status, data) of a REPLY payload, its tag checked."""
    f = split_signed(REPLY, payload)
    assert C.verify(KEY, f)
    status, data = C.parse_reply_body(f.body)
    return f.counter, status, data


# --- codec ------------------------------------------------------------------------------


@pytest.mark.parametrize("cmd", [
    Command(CMD_LEVEL, text="auto"),
    Command(CMD_LEVEL, text="mono_vo"),
    Command(CMD_POOL_COUNT, "stereo", count=2),
    Command(CMD_POOL_ACTIVATE, "mono"),
    Command(CMD_POOL_DEACTIVATE, "mono"),
    Command(CMD_POOL_POLICY, "vo", text="fifo:8"),
    Command(CMD_PARAM, "mono", text="confidence", value=0.5),
    Command(CMD_PARAM, "mono", text="n", value=-3),
    Command(CMD_PARAM, "mono", text="on", value=True),
    Command(CMD_PARAM, "mono", text="model", value="crab.onnx"),
    Command(CMD_PARAM, "mono", text="x", value=None),
    Command(CMD_STATUS),
    Command(CMD_HEALTH),
])
def test_command_round_trip_is_small(cmd: Command) -> None:
    body = command_body(cmd)
    assert parse_command_body(body) == cmd
    wire = frame(COMMAND, cmd_payload(7, cmd))
    assert len(wire) <= 6 + 4 + 1 + len(body) + TAG_BYTES
    assert len(wire) <= 60  # a few seconds at 300 bit/s
    (kind, payload), = Deframer().feed(wire)
    assert kind == COMMAND and split_signed(COMMAND, payload).body == body


def test_pool_count_command_is_36_bytes_on_the_wire() -> None:
    """The link budget of the typical command: 6 framing, 4 session, 1 counter, 9 body
    (kind, length, 'stereo', count), 16 tag: about 1.2 s at 300 bit/s."""
    assert len(frame(COMMAND, cmd_payload(7))) == 36


@pytest.mark.parametrize("body, error", [
    (b"", "expected 1 bytes"),
    (bytes((99,)), "expected a command kind"),
    (bytes((CMD_POOL_COUNT, 6)) + b"ste", "expected 6 bytes"),
    (bytes((CMD_STATUS, 0)), "expected 1 bytes of status"),
    (bytes((CMD_PARAM, 1)) + b"m" + bytes((1,)) + b"k" + bytes((9,)), "value type"),
    (bytes((CMD_LEVEL, 65)) + b"x" * 65, "at most 64"),
    (bytes((CMD_LEVEL, 2)) + b"\xff\xfe", "UTF-8"),
])
def test_malformed_command_bodies_say_what_was_expected(body: bytes, error: str) -> None:
    with pytest.raises(ProtocolError, match=error):
        parse_command_body(body)


def test_too_long_a_name_is_refused_when_encoding() -> None:
    with pytest.raises(ProtocolError, match="at most 64"):
        command_body(Command(CMD_LEVEL, text="x" * 65))


# --- HMAC ---------------------------------------------------------------------------------


def test_tag_covers_kind_session_counter_and_arguments() -> None:
    good = split_signed(COMMAND, cmd_payload(5))
    assert C.verify(KEY, good)
    assert not C.verify(OTHER_KEY, good)
    payload = cmd_payload(5)
    for i in range(len(payload) - TAG_BYTES):  # any changed byte before the tag
        bad = bytearray(payload)
        bad[i] ^= 0x01
        try:
            f = split_signed(COMMAND, bytes(bad))
        except ProtocolError:
            continue
        assert not C.verify(KEY, f), i
    # The same bytes as a REPLY do not verify: the frame type is signed.
    assert not C.verify(KEY, split_signed(REPLY, payload))


# --- counter rules (table) ---------------------------------------------------------------

FORGED = cmd_payload(10, key=OTHER_KEY)


@pytest.mark.parametrize("name, payload, decision, count, reply_status", [
    ("good", cmd_payload(6), C.Execute, "accepted", None),
    ("bad tag", FORGED, C.Refuse, "refused_tag", None),
    ("old counter", cmd_payload(4), C.Reply, "refused_old", REPLY_STALE),
    ("equal counter, other command", cmd_payload(5, Command(CMD_STATUS)), C.Reply,
     "refused_old", REPLY_STALE),
    ("replay of last", cmd_payload(5), C.Reply, "duplicates", REPLY_OK),
    ("truncated frame", cmd_payload(6)[:-3], C.Refuse, "refused_tag", None),
    ("shorter than a tag", cmd_payload(6)[:10], C.Refuse, "refused_malformed", None),
    ("unknown kind", cmd_payload(6, body=bytes((99,))), C.Execute, "accepted", None),
    ("other session", cmd_payload(6, session=b"\0\0\0\1"), C.Reply, "refused_session",
     REPLY_SESSION),
])
def test_counter_rules(name: str, payload: bytes, decision: type, count: str,
                       reply_status: int | None) -> None:
    guard = C.CommandGuard(KEY, SESSION, C.CounterState(session=SESSION.hex()))
    first = guard.receive(cmd_payload(5), 0.0)  # command 5 runs and is answered
    assert isinstance(first, C.Execute)
    guard.finished(5, REPLY_OK, {"changed": "stereo", "change": "count 1 -> 2"})
    before = guard.state.counter
    d = guard.receive(payload, 1.0)
    assert isinstance(d, decision), name
    assert guard.counts[count] == 1 + (count == "accepted"), name
    if isinstance(d, C.Reply):
        _, status, data = reply_of(d.payload)
        assert status == reply_status
        if status == REPLY_OK:  # the cached reply, byte for byte; nothing runs again
            assert data == {"changed": "stereo", "change": "count 1 -> 2"}
            assert guard.running is None
    if isinstance(d, C.Execute):
        assert guard.state.counter == 6 and guard.running == 6
        if name == "unknown kind":  # authentic, so the counter is taken; the reply says why
            assert d.command.kind == 0 and "command kind" in d.command.text
    else:
        assert guard.state.counter == before


def test_refusal_replies_are_rate_limited() -> None:
    """A replayed old frame must not spend the box's budget: one stale reply per interval
    for that frame; its first answer is fresh, the later ones repeats."""
    guard = C.CommandGuard(KEY, SESSION, C.CounterState(session=SESSION.hex(), counter=9))
    got = [guard.receive(cmd_payload(3), t) for t in (0.0, 1.0, 2.0, 6.0)]
    assert [type(d) for d in got] == [C.Reply, C.Refuse, C.Refuse, C.Reply]
    assert [d.repeat for d in got if isinstance(d, C.Reply)] == [False, True]
    assert guard.counts["refused_old"] == 4 and guard.counts["replies_held"] == 2


OTHER_SESSION = bytes.fromhex("0badf00d")


@pytest.mark.parametrize("name, frames, want", [
    # Issue 26 item 7: an old frame replayed once a second held the one slot, so the
    # surface's own command to the wrong session never heard its correction.
    ("replay, then the surface's command", [("old", 0.0), ("old", 1.0), ("new", 1.5),
                                            ("old", 2.0), ("new", 9.5)],
     [(True, False), (False, None), (True, False), (False, None), (True, True)]),
    # The surface's retransmissions (8 s apart) of its own frame are each answered.
    ("retries", [("new", 0.0), ("new", 8.0), ("new", 16.0)],
     [(True, False), (True, True), (True, True)]),
    # Two old frames replayed in turn: each once per interval, no more.
    ("two replays", [("old", 0.0), ("old2", 0.5), ("old", 1.0), ("old2", 1.5), ("old", 5.0)],
     [(True, False), (True, False), (False, None), (False, None), (True, True)]),
])
def test_refusal_replies_are_limited_per_frame(
        name: str, frames: list[tuple[str, float]], want: list[tuple[bool, bool | None]]
) -> None:
    guard = C.CommandGuard(KEY, SESSION, C.CounterState(session=SESSION.hex(), counter=9))
    payloads = {"old": cmd_payload(3), "old2": cmd_payload(4),
                "new": cmd_payload(10, session=OTHER_SESSION)}
    got = [guard.receive(payloads[which], t) for which, t in frames]
    assert [(isinstance(d, C.Reply), d.repeat if isinstance(d, C.Reply) else None)
            for d in got] == want, name
    for (which, _), d in zip(frames, got, strict=True):
        if which == "new" and isinstance(d, C.Reply):
            assert reply_of(d.payload)[1] == REPLY_SESSION, name


def test_answered_frames_are_bounded() -> None:
    guard = C.CommandGuard(KEY, SESSION, C.CounterState(session=SESSION.hex(), counter=5000))
    for c in range(C.MAX_ANSWERED_FRAMES + 50):
        assert isinstance(guard.receive(cmd_payload(c + 1), 0.0), C.Reply)
    assert len(guard._answered) == C.MAX_ANSWERED_FRAMES


@pytest.mark.parametrize("name, reply_saved, times, want", [
    # a replay 3 times a second: one answer per interval, the interval growing 1.5 times
    # an answer (issue 36 item 2), the rest held and counted
    ("cached, replayed 3/s", True, [0.0, 0.33, 0.66, 1.0, 4.9, 5.0, 5.3, 10.1, 12.5, 23.0,
                                    23.8],
     [True, False, False, False, False, True, False, False, True, False, True]),
    # the surface's own retransmissions (8 s, then 1.5 times longer each, up to 60 s) are
    # each answered, however long it goes on
    ("cached, surface retries", True, [0.0, 8.0, 20.0, 38.0, 65.0, 105.5, 165.5, 225.5],
     [True] * 8),
    # "reply lost" (taken before a restart) is limited the same way
    ("lost, replayed 3/s", False, [0.0, 0.33, 0.66, 5.0], [True, False, False, True]),
])
def test_repeated_answers_are_rate_limited_per_command(
        name: str, reply_saved: bool, times: list[float], want: list[bool]) -> None:
    """Regression for issue 26 item 1: every replay of the last accepted command got its
    cached reply, so a recorded frame replayed 3 times a second drained the hourly budget.
    Now at most one answer per REPEAT_REPLY_INTERVAL_S per command, marked a repeat (the
    sender gives repeats only a share of the budget), and the held ones are counted."""
    state = C.CounterState(session=SESSION.hex(), counter=5, tag=split_signed(
        COMMAND, cmd_payload(5)).tag.hex())
    guard = C.CommandGuard(KEY, SESSION, state)
    if reply_saved:
        guard.finished(5, REPLY_OK, {"changed": "stereo", "change": "count 1 -> 2"})
    got = [guard.receive(cmd_payload(5), t) for t in times]
    assert [isinstance(d, C.Reply) for d in got] == want, name
    assert all(d.repeat for d in got if isinstance(d, C.Reply)), name
    assert guard.counts["duplicates"] == len(times)
    assert guard.counts.get("replies_held", 0) == want.count(False)
    status = REPLY_OK if reply_saved else REPLY_LOST
    assert {reply_of(d.payload)[1] for d in got if isinstance(d, C.Reply)} == {status}


def test_a_new_command_is_answered_at_once_after_replays_of_the_last() -> None:
    """The replays' interval is per command: the next command's answer is fresh (not a
    repeat), and its own retransmission gets the cached reply at once."""
    guard = C.CommandGuard(KEY, SESSION, C.CounterState(session=SESSION.hex()))
    assert isinstance(guard.receive(cmd_payload(1), 0.0), C.Execute)
    guard.finished(1, REPLY_OK, {})
    assert isinstance(guard.receive(cmd_payload(1), 0.1), C.Reply)
    assert isinstance(guard.receive(cmd_payload(1), 0.2), C.Refuse)
    assert isinstance(guard.receive(cmd_payload(2), 0.3), C.Execute)
    payload, _ = guard.finished(2, REPLY_OK, {})
    again = guard.receive(cmd_payload(2), 0.4)
    assert isinstance(again, C.Reply) and again.payload == payload and again.repeat
    busy_guard = C.CommandGuard(KEY, SESSION, C.CounterState(session=SESSION.hex()))
    busy_guard.receive(cmd_payload(1), 0.0)
    busy = busy_guard.receive(cmd_payload(2), 0.1)
    assert isinstance(busy, C.Reply) and not busy.repeat  # only a new counter asks for it


def test_busy_while_a_command_runs_and_retransmission_while_it_runs_is_dropped() -> None:
    guard = C.CommandGuard(KEY, SESSION, C.CounterState(session=SESSION.hex()))
    assert isinstance(guard.receive(cmd_payload(1), 0.0), C.Execute)
    again = guard.receive(cmd_payload(1), 0.1)
    assert isinstance(again, C.Refuse) and again.kind == "duplicates"
    busy = guard.receive(cmd_payload(2), 0.2)
    assert isinstance(busy, C.Reply) and reply_of(busy.payload)[1] == REPLY_BUSY
    assert guard.state.counter == 1  # 2 not taken: it is sent again and runs later
    guard.finished(1, REPLY_OK, {})
    assert isinstance(guard.receive(cmd_payload(2), 0.3), C.Execute)


def test_no_key_refuses_everything() -> None:
    guard = C.CommandGuard(None, SESSION, C.CounterState(session=SESSION.hex()))
    d = guard.receive(cmd_payload(1), 0.0)
    assert isinstance(d, C.Refuse) and "command_key" in d.why


def test_a_corrupt_counter_file_refuses_every_command() -> None:
    """Starting from 0 would let this session's old commands run again: refuse them all."""
    guard = C.CommandGuard(KEY, SESSION, C.CounterState(session=SESSION.hex()),
                           disabled="command counter file x is corrupt")
    d = guard.receive(cmd_payload(100), 0.0)
    assert isinstance(d, C.Refuse) and d.kind == "refused_disabled" and "corrupt" in d.why


def test_counter_survives_a_restart_and_a_lost_reply_is_never_run_again(tmp_path: Path
                                                                       ) -> None:
    """The box saves the counter before running; after a power cut between running and
    saving the reply, a retransmission gets 'lost', never a second execution."""
    path = tmp_path / "commands.json"
    guard = C.CommandGuard(KEY, SESSION, C.load_counter(path, SESSION))
    d = guard.receive(cmd_payload(3), 0.0)
    assert isinstance(d, C.Execute)
    C.save_counter(path, d.state)
    # power cut here: the reply was never saved
    guard = C.CommandGuard(KEY, SESSION, C.load_counter(path, SESSION))
    assert guard.state.counter == 3
    again = guard.receive(cmd_payload(3), 0.0)
    assert isinstance(again, C.Reply) and reply_of(again.payload)[1] == REPLY_LOST
    assert isinstance(guard.receive(cmd_payload(2), 0.0), C.Reply)  # stale
    # and once the reply was saved, a retransmission gets it
    payload, state = guard.finished(3, REPLY_OK, {"changed": "x", "change": "y"})
    C.save_counter(path, state)
    guard = C.CommandGuard(KEY, SESSION, C.load_counter(path, SESSION))
    cached = guard.receive(cmd_payload(3), 0.0)
    assert isinstance(cached, C.Reply) and cached.payload == payload
    # another outbox session starts from 0: its commands name that session anyway
    assert C.load_counter(path, b"\1\2\3\4").counter == 0
    path.write_text("{not json")
    with pytest.raises(ConfigError, match="corrupt"):
        C.load_counter(path, SESSION)


COUNT_3 = Command(CMD_POOL_COUNT, "stereo", count=3)
LOST_CHANGE = "no longer applies"  # the words of a cached reply from an earlier start
LOST_REPLY = "its reply is lost"


@pytest.mark.parametrize("taken_in, now_in, cmd, replied, status, words", [
    # the modem node restarted within one run of the box: the change still holds, "ok"
    ("run-a", "run-a", COUNT_3, True, REPLY_OK, "count 1 -> 3"),
    # a power cut: the box runs its configured count again, so "ok" would be false
    ("run-a", "run-b", COUNT_3, True, REPLY_LOST, LOST_CHANGE),
    # the same for any command: a status of a run that ended says nothing of this one
    ("run-a", "run-b", Command(CMD_STATUS), True, REPLY_LOST, LOST_CHANGE),
    # taken, then the power went before its reply was saved
    ("run-a", "run-b", COUNT_3, False, REPLY_LOST, LOST_CHANGE),
    # taken, then the modem node died before its reply was saved (the run goes on)
    ("run-a", "run-a", COUNT_3, False, REPLY_LOST, LOST_REPLY),
    # a counter file saved before runs were named predates this start too
    ("", "run-b", COUNT_3, True, REPLY_LOST, LOST_CHANGE),
])
def test_a_cached_reply_after_a_restart_says_the_change_was_lost(
        tmp_path: Path, taken_in: str, now_in: str, cmd: Command, replied: bool,
        status: int, words: str) -> None:
    """Issue 26 item 6: `pool stereo --count 3` ran, its reply was lost, the box lost power;
    the retransmission got the cached "ok, count 1 -> 3" while the restarted box ran 1
    worker. Runtime changes end with the run that made them: a cached reply is repeated only
    in the run it was made in, and after a restart the surface hears the change was lost.
    The command never runs twice either way."""
    path = tmp_path / "commands.json"
    before = C.CommandGuard(KEY, SESSION, C.load_counter(path, SESSION), run=taken_in)
    d = before.receive(cmd_payload(3, cmd), 0.0)
    assert isinstance(d, C.Execute)
    C.save_counter(path, d.state)  # before it runs
    if replied:
        _, state = before.finished(3, REPLY_OK, {"changed": "stereo", "change": "count 1 -> 3"})
        C.save_counter(path, state)
    after = C.CommandGuard(KEY, SESSION, C.load_counter(path, SESSION), run=now_in)
    again = after.receive(cmd_payload(3, cmd), 0.0)
    assert isinstance(again, C.Reply) and again.repeat
    counter, got, data = reply_of(again.payload)
    assert (counter, got) == (3, status)
    assert words in str(data), data
    assert "accepted" not in after.counts  # never executed again


def test_reply_body_fits_one_frame() -> None:
    long = {"error": "x" * 400}
    body = C.reply_body(REPLY_ERROR, long)
    assert len(body) <= C.MAX_REPLY_BODY
    status, data = C.parse_reply_body(body)
    assert status == REPLY_ERROR and data["error"].endswith("...")
    pools = {"status": {"uptime_s": 5}, "pools": {f"pool{i}": ["active", 2, 10**6, 3, 1.5]
                                                   for i in range(30)}}
    body = C.reply_body(REPLY_OK, pools)
    assert len(body) <= C.MAX_REPLY_BODY
    assert C.parse_reply_body(body)[1] == {"status": {"uptime_s": 5}, "cut": True}
    assert len(frame(REPLY, C.sign(KEY, REPLY, SESSION, 2**35, body))) <= MAX_PAYLOAD + 6


# --- command -> control request ---------------------------------------------------------


@pytest.mark.parametrize("cmd, expected", [
    (Command(CMD_LEVEL, text="auto"), control_msgs.LevelRequest(level="auto")),
    (Command(CMD_POOL_COUNT, "stereo", count=2), control_msgs.PoolRequest(pool="stereo", count=2)),
    (Command(CMD_POOL_ACTIVATE, "mono"), control_msgs.PoolRequest(pool="mono", active=True)),
    (Command(CMD_POOL_DEACTIVATE, "mono"), control_msgs.PoolRequest(pool="mono", active=False)),
    (Command(CMD_POOL_POLICY, "vo", text="fifo:8"),
     control_msgs.PoolRequest(pool="vo", policy="fifo:8")),
    (Command(CMD_PARAM, "mono", text="confidence", value=0.5),
     control_msgs.ParamRequest(pool="mono", key="confidence", value=0.5)),
    (Command(CMD_STATUS), control_msgs.StatusRequest()),
    (Command(CMD_HEALTH), None),
])
def test_each_command_becomes_its_control_request(cmd: Command, expected: object) -> None:
    req = C.control_request(cmd)
    assert req == expected
    if req is not None:  # and the supervisor's decoder takes it
        assert control_msgs.decode_control(messages.encode(req)) == req


# --- key file ------------------------------------------------------------------------------


@pytest.mark.parametrize("mode, content, error", [
    (0o600, bytes(range(7, 7 + 32)), None),
    (0o400, bytes(range(7, 7 + 16)), None),
    (0o640, bytes(range(7, 7 + 32)), "readable by group or others .mode 640.*chmod 600"),
    (0o604, bytes(range(7, 7 + 32)), "mode 604"),
    (0o600, b"short", "at least 16 bytes, got 5"),
])
def test_key_file_rules(tmp_path: Path, mode: int, content: bytes, error: str | None) -> None:
    path = tmp_path / "key"
    path.write_bytes(content)
    path.chmod(mode)
    if error is None:
        assert C.load_key(path) == content
    else:
        with pytest.raises(ConfigError, match=error):
            C.load_key(path)


def test_missing_key_file_names_how_to_make_one(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="head -c 32 /dev/urandom"):
        C.load_key(tmp_path / "nope")


# --- grammar -------------------------------------------------------------------------------


@pytest.mark.parametrize("text, cmd, error", [
    ("level auto", Command(CMD_LEVEL, text="auto"), None),
    ("pool stereo --count 2", Command(CMD_POOL_COUNT, "stereo", count=2), None),
    ("pool mono --deactivate", Command(CMD_POOL_DEACTIVATE, "mono"), None),
    ("pool mono --activate", Command(CMD_POOL_ACTIVATE, "mono"), None),
    ("pool vo --policy fifo:8", Command(CMD_POOL_POLICY, "vo", text="fifo:8"), None),
    ("param mono confidence=0.5", Command(CMD_PARAM, "mono", text="confidence", value=0.5),
     None),
    ("status", Command(CMD_STATUS), None),
    ("health", Command(CMD_HEALTH), None),
    ("", None, "got none"),
    ("reboot", None, "got 'reboot'"),
    ("pool stereo --count two", None, "expected a number, got 'two'"),
    ("pool stereo", None, "expected `pool NAME"),
    ("level", None, "expected `level NAME"),
    ("param mono confidence", None, "KEY=VALUE"),
    ("status now", None, "expected `status`"),
])
def test_grammar(text: str, cmd: Command | None, error: str | None) -> None:
    if error is None:
        assert C.parse_command_text(text) == cmd
    else:
        with pytest.raises(ValueError, match=error):
            C.parse_command_text(text)


# --- the surface's client --------------------------------------------------------------------


def test_surface_counter_is_saved_before_use_and_never_reused(tmp_path: Path) -> None:
    path = tmp_path / "key.counter"
    assert [take_counter(path) for _ in range(3)] == [1, 2, 3]
    assert take_counter(path, at_least=10) == 10
    assert take_counter(path) == 11


def test_client_follows_session_and_stale_corrections_signed_by_the_box(tmp_path: Path
                                                                        ) -> None:
    """A fresh outbox on the box and a lost counter file at the surface: the box's signed
    replies lead the command to the right session and above the last counter; then it runs
    once."""
    box = C.CommandGuard(KEY, SESSION, C.CounterState(session=SESSION.hex(), counter=41))
    client = CommandClient(KEY, tmp_path / "c", bytes(4), Command(CMD_STATUS), retry_s=1.0)
    now = 0.0
    for _ in range(10):
        wire = client.due(now)
        if wire is not None:
            (_, payload), = Deframer().feed(wire)
            d = box.receive(payload, now)
            if isinstance(d, C.Execute):
                client.on_reply(box.finished(d.counter, REPLY_OK, {"status": {"up": 1}})[0])
            elif isinstance(d, C.Reply):
                client.on_reply(d.payload)
        if client.done:
            break
        now += 6.0  # past the box's refusal-reply interval
    assert client.ok and client.session == SESSION and client.counter == 42
    assert client.outcome() == {"reply": "ok", "counter": 42, "session": SESSION.hex(),
                                "status": {"up": 1}}
    assert box.counts["accepted"] == 1 and client.counts["corrections"] == 2
    # a forged reply with our counter is ignored
    client2 = CommandClient(OTHER_KEY, tmp_path / "c", SESSION, Command(CMD_STATUS))
    client2.on_reply(box.reply(client2.counter, REPLY_OK, {}))
    assert not client2.done and client2.counts["forged_replies"] == 1


# --- the box's control client: bounded, never blocking ----------------------------------------


def test_control_client_answers_or_gives_up_in_time(tmp_path: Path,
                                                    zctx: zmq.Context[zmq.Socket[bytes]]
                                                    ) -> None:
    """A supervisor that does not answer costs the modem loop nothing: poll() returns at
    once, and after the timeout an error reply says the change may still be made."""
    endpoint = f"ipc://{tmp_path}/control"
    rep = open_socket(zctx, SocketSpec(zmq.REP, endpoint, bind=True))
    client = ControlClient(zctx, endpoint)
    try:
        client.send(control_msgs.StatusRequest(), 5.0, now=100.0)
        assert client.busy
        assert control_msgs.decode_control(recv(rep)[0]) == control_msgs.StatusRequest()
        rep.send(b'{"uptime_s": 3}')
        reply = poll_for(lambda: client.poll(101.0), 5, what="the reply")
        assert reply == {"uptime_s": 3} and not client.busy
        # No answer this time: nothing until the deadline, then an error, not a hang.
        client.send(control_msgs.LevelRequest(level="auto"), 2.0, now=200.0)
        recv(rep)
        t0 = time.monotonic()
        assert client.poll(201.0) is None
        late = client.poll(202.5)
        assert time.monotonic() - t0 < 0.5
        assert late is not None and "did not answer within 2 s" in late["error"]
        assert not client.busy
    finally:
        client.close()
        rep.close(linger=0)
