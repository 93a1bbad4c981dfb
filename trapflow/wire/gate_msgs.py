"""Normalizer -> broker over the results link, besides acknowledgements: what the motion
gate should know from the observations (tracks alive) and from visual odometry (the rig
moves). The link is the local, single-peer one the results use: no other process can speak."""

from __future__ import annotations

from typing import Annotated

import msgspec

from trapflow.errors import ProtocolError
from trapflow.wire.messages import MAX_HEADER_BYTES, Buffer, Msg, ResultsAck, decode_bounded


class GateHint(Msg, frozen=True, tag="gate_hint"):
    """Tracks alive now (over every detector pool) and whether the rig moves."""

    tracks: Annotated[int, msgspec.Meta(ge=0, le=1 << 20)] = 0
    rig_moving: bool = False


NormalizerMsg = ResultsAck | GateHint

_normalizer_dec = msgspec.msgpack.Decoder(NormalizerMsg)


def decode_normalizer_msg(data: Buffer) -> NormalizerMsg:
    """Decode what the normalizer sent on the results link (an ack or a gate hint)."""
    msg: NormalizerMsg = decode_bounded(_normalizer_dec, data, "normalizer message",
                                        MAX_HEADER_BYTES)
    if isinstance(msg, ResultsAck) and msg.count < 0:
        raise ProtocolError(f"results ack: expected a count >= 0, got {msg.count}")
    return msg
