"""Wire format: round trips, and every malformed shape rejected with a reason."""

from __future__ import annotations

import re

import msgspec
import numpy as np
import pytest

from tests import builders
from trapflow.errors import ProtocolError
from trapflow.wire import frame_msgs, messages, tap_msgs


def test_pair_roundtrip() -> None:
    frames = builders.pair_frames(seq=5)
    pair = messages.check_pair_frames(frames)
    assert pair.seq == 5 and pair.width == 64 and pair.encoding == "jpeg"


def test_result_roundtrip_every_body() -> None:
    bodies: list[messages.Body] = [
        messages.MonoIR(detections=[messages.Detection(label="crab", confidence=0.5,
                                                       box=(1, 2, 3, 4))]),
        messages.StereoIR(label="scallop", confidence=0.9),
        messages.StereoVO(ok=True, rotation=(1.0,) * 9, translation=(0.1, 0, 0)),
        messages.Tags(tags=[messages.Tag(id=3, corners=[(0, 0), (1, 0), (1, 1), (0, 1)])]),
        messages.Extra(name="x", fields={"a": 1}),
    ]
    for body in bodies:
        res = builders.result(body)
        assert messages.decode_result(messages.encode(res)) == res


def test_numpy_scalars_encode_as_numbers() -> None:
    det = messages.Detection(label="crab", confidence=np.float32(0.5),  # type: ignore[arg-type]
                             box=(np.float64(1), 2, 3, 4))  # type: ignore[arg-type]
    out = msgspec.msgpack.decode(messages.encode(det))
    assert out["confidence"] == 0.5 and out["box"][0] == 1.0


def _header(**kw: object) -> bytes:
    fields = msgspec.structs.asdict(builders.pair_header())
    fields.update(kw)
    return msgspec.msgpack.encode({"type": "pair", **fields})


GOOD = builders.pair_frames()


@pytest.mark.parametrize(
    ("frames", "error"),
    [
        (GOOD[:2], "expected 3 frames"),
        ([*GOOD, b"extra"], "expected 3 frames"),
        ([b"\x85garbage", GOOD[1], GOOD[2]], "pair header"),
        ([GOOD[0][:-5], GOOD[1], GOOD[2]], "pair header"),
        ([b"x" * 5000, GOOD[1], GOOD[2]], "at most 4096 bytes"),
        ([_header(seq="one"), GOOD[1], GOOD[2]], "Expected `int`"),
        ([_header(width=0), GOOD[1], GOOD[2]], "width and height"),
        ([_header(width=100000), GOOD[1], GOOD[2]], "width and height"),
        ([_header(seq=-1), GOOD[1], GOOD[2]], "seq >= 0"),
        ([_header(encoding="png"), GOOD[1], GOOD[2]], "Invalid enum value .png."),
        ([GOOD[0], b"", GOOD[2]], "left JPEG expected"),
        ([_header(encoding="raw"), b"x" * 10, GOOD[2]], "left raw image expected 9216"),
        ([messages.encode(messages.Ready(worker="a", pool="b")), GOOD[1], GOOD[2]],
         "pair header"),
    ],
)
def test_malformed_pairs_rejected(frames: list[bytes], error: str) -> None:
    with pytest.raises(ProtocolError, match=error):
        messages.check_pair_frames(frames)


@pytest.mark.parametrize(
    ("data", "error"),
    [
        (b"", "worker message"),
        (b"\xc1", "worker message"),
        (msgspec.msgpack.encode({"type": "nope"}), "Invalid value 'nope'"),
        (msgspec.msgpack.encode({"type": "done", "worker": "w", "pool": "p"}),
         "missing required field `seq`"),
        (msgspec.msgpack.encode([1, 2, 3]), "Expected `object`"),
    ],
)
def test_malformed_worker_messages_rejected(data: bytes, error: str) -> None:
    with pytest.raises(ProtocolError, match=error):
        messages.decode_worker_msg(data)


def test_result_size_limit() -> None:
    with pytest.raises(ProtocolError, match="at most"):
        messages.decode_result(b"\x00" * (messages.MAX_RESULT_BYTES + 1))


def test_link_frames_roundtrip() -> None:
    frames = [b"job", b"", memoryview(b"header"), bytearray(b"\x00" * 300)]
    out = frame_msgs.unpack_frames(frame_msgs.pack_frames(frames))
    assert [bytes(f) for f in out] == [bytes(f) for f in frames]


@pytest.mark.parametrize(("data", "error"), [
    (b"", "empty datagram"),
    (b"\x00", "got count 0"),
    (bytes([frame_msgs.MAX_LINK_FRAMES + 1]) + b"\x00" * 400, "got count 65"),
    (b"\x02\x01\x00\x00\x00", "got count 2 in 5 bytes"),
    (b"\x01\x05\x00\x00\x00ab", "add up to 10 bytes, datagram has 7"),
    (b"\x01\x01\x00\x00\x00abc", "add up to 6 bytes, datagram has 8"),
])
def test_link_frames_reject_malformed(data: bytes, error: str) -> None:
    with pytest.raises(ProtocolError, match=error):
        frame_msgs.unpack_frames(data)


@pytest.mark.parametrize("count", [0, frame_msgs.MAX_LINK_FRAMES + 1])
def test_link_frames_refuse_to_pack_a_wrong_count(count: int) -> None:
    with pytest.raises(ProtocolError, match="frames"):
        frame_msgs.pack_frames([b"x"] * count)


def _stats() -> messages.Stats:
    return messages.Stats(t_wall_ns=1, uptime_s=2.0, pairs_in=3, rate_in=1.5, malformed=0,
                          pools={})


def test_every_tap_topic_is_decoded_by_one_function() -> None:
    header, left, right = builders.pair_frames(seq=4)
    pair = tap_msgs.decode_tap([tap_msgs.TOPIC_IMAGE, header, left, right])
    assert isinstance(pair, tap_msgs.TapPair) and pair.header.seq == 4
    assert bytes(pair.left) == left and bytes(pair.right) == right
    meta = tap_msgs.decode_tap([tap_msgs.TOPIC_META, header])
    assert isinstance(meta, tap_msgs.TapMeta) and meta.header == pair.header
    stats = tap_msgs.decode_tap([tap_msgs.TOPIC_STATS, messages.encode(_stats())])
    assert isinstance(stats, tap_msgs.TapStats) and stats.stats == _stats()
    line = b'{"mono_ir": {"seq": 4, "label": "crab"}}'
    res = tap_msgs.decode_tap([tap_msgs.TOPIC_RESULT, line])
    assert res == tap_msgs.TapResult("mono_ir", {"seq": 4, "label": "crab"}, line)
    truth = messages.Truth(seq=4, pose=(1.0,) * 12)
    got = tap_msgs.decode_tap([tap_msgs.TOPIC_TRUTH, messages.encode(truth)])
    assert isinstance(got, tap_msgs.TapTruth) and got.truth == truth


def test_tap_frames_received_without_copy_are_decoded_in_place() -> None:
    zmq = pytest.importorskip("zmq")
    header, left, right = builders.pair_frames(seq=2)
    msg = tap_msgs.decode_tap([zmq.Frame(f) for f in (tap_msgs.TOPIC_IMAGE, header, left,
                                                      right)])
    assert isinstance(msg, tap_msgs.TapPair) and isinstance(msg.left, memoryview)
    assert bytes(msg.left) == left


@pytest.mark.parametrize(("frames", "error"), [
    ([], "got an empty message"),
    ([b"image", b"x"], "expected image [topic, header, left, right]"),
    ([b"result", b"{}", b"{}"], "with 3 frames"),
    ([b"bogus", b"x"], "got topic b'bogus'"),
    ([b"result", b'{"a": {}, "b": {}}'], "expected one key"),
    ([b"result", b"x" * (messages.MAX_RESULT_BYTES + 1)], "at most"),
    ([b"stats", b"\x01"], "stats"),
    ([b"image", *builders.pair_frames()[:2], b""], "JPEG expected 1.."),
])
def test_malformed_tap_messages_say_what_was_expected(frames: list[bytes], error: str) -> None:
    with pytest.raises(ProtocolError, match=re.escape(error)):
        tap_msgs.decode_tap(frames)
