"""One pair through one plugin, as a worker and a batch chunk both do it (process_pair):
decoded as the plugin asks, decoded once per need across plugins, stamped with the rig's
id, and the result carrying the header's times.

Regression: batch/chunk.py copied the worker's decode-process-result path, so the two could
drift (a stamp or a time taken differently offline than live)."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from tests import builders
from trapflow.errors import ProtocolError
from trapflow.plugin import Pair, Worker
from trapflow.pools.pair_path import Need, process_pair
from trapflow.wire import messages


class _Seen(Worker):
    """Answers with what it was given: the image shape and whether it was bytes."""

    def __init__(self, colour: str = "bgr", needs_images: bool = True,
                 body: str = "vo") -> None:
        self.colour = colour
        self.needs_images = needs_images
        self.body = body
        self.seen: list[Pair] = []

    def process(self, pair: Pair) -> messages.Body:
        self.seen.append(pair)
        if self.body == "vo":
            return messages.StereoVO(ok=True)
        if self.body == "vo-own-calib":
            return messages.StereoVO(ok=True, calib="its-own")
        return messages.Extra(name="shape", fields={"shape": list(pair.left.shape)})


def _frames() -> tuple[messages.StereoPair, bytes, bytes]:
    header = builders.pair_header(5, 64, 48, "jpeg")
    left, right = builders.image(64, 48, 1), builders.image(64, 48, 2)
    return header, builders.jpeg(left), builders.jpeg(right)


@pytest.mark.parametrize(("plugin", "want_shape", "want_calib"), [
    (_Seen(), (48, 64, 3), "rig-1"),  # a stereo body without a calib gets the rig's id
    (_Seen(body="vo-own-calib"), (48, 64, 3), "its-own"),  # a plugin's own stamp is kept
    (_Seen(colour="grey", body="extra"), (48, 64), None),  # grey: decoded straight to grey
    (_Seen(needs_images=False, body="extra"), None, None),  # the JPEG bytes, not decoded
])
def test_one_pair_through_one_plugin(plugin: _Seen, want_shape: Any, want_calib: Any) -> None:
    header, left, right = _frames()
    got = process_pair(plugin, header, left, right, pool="p", worker="w:1", calib="rig-1",
                       gap=2)
    r = got.result
    assert (r.seq, r.t_wall_ns, r.t_mono_ns, r.pool, r.worker) == (
        5, header.t_wall_ns, header.t_mono_ns, "p", "w:1")
    assert r.proc_ns >= 0 and got.cpu_ns >= 0 and got.pair.gap == 2
    if want_shape is None:
        assert got.pair.left.tobytes() == left  # the encoded bytes as they came
    else:
        assert got.pair.left.shape == want_shape
    if want_calib is not None:
        assert isinstance(r.body, messages.StereoVO) and r.body.calib == want_calib


def test_a_pair_is_decoded_once_per_need_across_plugins() -> None:
    header, left, right = _frames()
    decoded: dict[Need, Pair] = {}
    a, b, grey = _Seen(), _Seen(), _Seen(colour="grey")
    for plugin in (a, b, grey):
        process_pair(plugin, header, left, right, pool="p", worker="w", calib="c",
                     decoded=decoded)
    assert a.seen[0] is b.seen[0]  # the same decoded pair, not decoded again
    assert grey.seen[0] is not a.seen[0] and len(decoded) == 2
    assert np.array_equal(a.seen[0].left, b.seen[0].left)


def test_an_undecodable_frame_raises_for_the_caller_to_fail_the_pair() -> None:
    header, left, _ = _frames()
    with pytest.raises(ProtocolError, match="right image is not a decodable JPEG"):
        process_pair(_Seen(), header, left, b"not a jpeg", pool="p", worker="w", calib="c")
