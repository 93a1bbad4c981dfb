"""A queued track's thumbnail from the box to the surface: the worker crops confident
boxes while it holds the pixels, the best crop of a track is kept, its thumbnail travels
as `thumb` records that each decode on their own (the link codec's kind 11, within the
byte budget), and the surface writes one JPEG per track from whatever packets arrived."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from tests import builders
from trapflow.config.schema import ModemConfig, ReviewConfig
from trapflow.modem import thumb
from trapflow.modem.codec import LinkCodec
from trapflow.modem.frame import max_body
from trapflow.modem.surface_thumb import Thumbnails
from trapflow.plugin import Pair
from trapflow.pools.pair_path import ViewPacer, ViewSpec, crop_views
from trapflow.tracking.review import Reviewer
from trapflow.wire import messages


def _scene(w: int = 640, h: int = 480) -> np.ndarray:
    rng = np.random.default_rng(5)
    img = cv2.GaussianBlur(rng.integers(0, 255, (h, w, 3), dtype=np.uint8), (0, 0), 2)
    cv2.circle(img, (200, 150), 40, (0, 0, 255), -1)
    return img


def _det(conf: float, box: tuple[float, float, float, float]) -> messages.Detection:
    return messages.Detection(label="crab", confidence=conf, box=box)


def test_the_worker_crops_confident_boxes_from_the_reduced_image() -> None:
    frame = _scene()
    half = cv2.resize(frame, (320, 240), interpolation=cv2.INTER_AREA)
    pair = Pair(header=builders.pair_header(), left=half, right=half, reduction=2)
    body = messages.MonoIR(detections=[
        _det(0.9, (100.0, 60.0, 400.0, 260.0)),  # frame pixels: 300 x 200
        _det(0.3, (0.0, 0.0, 100.0, 100.0)),  # below min_confidence: no crop
        _det(0.8, (10.0, 10.0, 16.0, 16.0)),  # 3 px in the reduced image: no crop
    ])
    out = crop_views(body, pair, ViewSpec(min_confidence=0.5, crop_px=128))
    assert isinstance(out, messages.MonoIR)
    assert [v.box for v in out.views] == [(100.0, 60.0, 400.0, 260.0)]
    crop = cv2.imdecode(np.frombuffer(out.views[0].jpeg, np.uint8), cv2.IMREAD_COLOR)
    assert crop.shape[:2] == (85, 128)  # 150 x 100 reduced pixels shrunk to 128 wide
    assert out.views[0].sharpness > 0
    # bytes only (a plugin with needs_images False gets the encoded bytes), or not a
    # detector: unchanged (cropping the bytes failed every pair of such a detector)
    encoded = Pair(header=builders.pair_header(), left=np.zeros(1000, np.uint8),
                   right=np.zeros(1000, np.uint8))
    assert crop_views(body, encoded, ViewSpec(0.5, 128)) == body
    assert crop_views(messages.StereoVO(ok=True), pair, ViewSpec(0.5, 128)) == \
        messages.StereoVO(ok=True)
    # the view survives the wire
    assert messages.decode_result(messages.encode(builders.result(out))).body == out


def test_a_worker_crops_one_pair_a_second_of_capture_time() -> None:
    import msgspec

    pacer = ViewPacer(ViewSpec(0.5, 128, every_s=1.0))
    with_view = messages.MonoIR(views=[messages.BoxView(box=(0, 0, 9, 9), jpeg=b"j",
                                                        sharpness=1.0)])

    def at(s: float) -> messages.StereoPair:
        return msgspec.structs.replace(builders.pair_header(), t_mono_ns=int(s * 1e9))

    assert pacer.due(at(10.0)) is not None
    pacer.done(at(10.0), messages.MonoIR())  # no crop: the next pair is due still
    assert pacer.due(at(10.1)) is not None
    pacer.done(at(10.1), with_view)
    assert pacer.due(at(10.5)) is None and pacer.due(at(11.1)) is not None
    assert pacer.due(at(3.0)) is not None  # the clock went back: due


def test_a_track_keeps_its_largest_sharpest_most_confident_crop() -> None:
    reviewer = Reviewer(ReviewConfig(crop_px=128), "mono")
    small = (0.0, 0.0, 32.0, 32.0)
    large = (0.0, 0.0, 200.0, 120.0)
    assert reviewer.offer_crop(3, 0.6, small, 500.0, b"small", 1.0)
    assert reviewer.offer_crop(3, 0.6, large, 500.0, b"large", 2.0)
    assert not reviewer.offer_crop(3, 0.6, large, 5.0, b"blurred", 3.0)
    assert reviewer.views[3].jpeg == b"large"


def _packets(budget: int = 256) -> list[thumb.Packet]:
    crop = _scene()[100:220, 140:300]
    return thumb.fit(crop, budget)


@pytest.mark.parametrize("budget", [128, 256, 512])
@pytest.mark.parametrize("track", [4, 300])
def test_thumb_records_ride_the_link_codec_within_the_budget(budget: int, track: int) -> None:
    codec = LinkCodec()
    packets = _packets(budget)
    bodies = [codec.encode(thumb.record(track, p)) for p in packets]
    assert all(b[0] == 11 for b in bodies)  # the compact kind, never generic
    assert sum(map(len, bodies)) <= budget
    assert max(map(len, bodies)) <= max_body(ModemConfig().max_frame_payload)  # a frame each
    for body, p in zip(bodies, packets, strict=True):
        assert thumb.from_record(codec.decode(body)["thumb"]) == (track, p)


def test_a_smaller_frame_gets_smaller_packets() -> None:
    codec = LinkCodec()
    most = thumb.max_packet(max_body(48))
    packets = thumb.fit(_scene()[100:220, 140:300], 256, True, most)
    assert packets and all(len(p.data) <= most for p in packets)
    assert max(len(codec.encode(thumb.record(200, p))) for p in packets) <= max_body(48)


def test_thumbnails_rank_below_the_news_and_above_per_pair_detections() -> None:
    cfg = ModemConfig()
    rank = cfg.priority_of
    assert rank("new_label") < rank("track") < rank("thumb") < rank("mono_ir/crab")
    assert rank("thumb") < rank("stereo_ir/scallop") and cfg.ttl_of("thumb") == 0.0
    assert not cfg.aggregates("thumb") and not cfg.is_news("thumb")


def test_the_surface_writes_a_jpeg_from_the_packets_that_arrived(tmp_path: Path) -> None:
    packets = _packets(512)
    assert len(packets) >= 3
    whole = thumb.decode(packets).astype(int)
    lost = 1
    session = bytes.fromhex("8c41d20e")
    store = Thumbnails(tmp_path / "review")
    lines = [store.add(session, thumb.record(7, p)["thumb"])
             for i, p in enumerate(packets) if i != lost]
    path = tmp_path / "review" / "8c41d20e-7.jpg"
    assert lines[-1]["file"] == "review/8c41d20e-7.jpg" and "data" not in lines[-1]
    assert lines[-1]["of"] == thumb.total_segments(packets[0])
    assert lines[-1]["segments"] == lines[-1]["of"] - thumb.segment_count(packets[lost])
    img = cv2.imread(str(path), cv2.IMREAD_COLOR).astype(int)
    assert img.shape == whole.shape == (packets[0].height, packets[0].width, 3)
    rows = np.abs(img - whole).reshape(img.shape[0], -1).max(axis=1) > 0
    assert 0 < rows.sum() < img.shape[0]  # the lost packet's rows only
    # a restarted surface keeps the packets before; the lost one completes the picture
    again = Thumbnails(tmp_path / "review")
    line = again.add(session, thumb.record(7, packets[lost])["thumb"])
    assert line["segments"] == line["of"]
    assert (cv2.imread(str(path), cv2.IMREAD_COLOR).astype(int) == whole).all()


def test_a_bad_packet_is_one_line_and_nothing_written(tmp_path: Path) -> None:
    store = Thumbnails(tmp_path / "review")
    line = store.add(b"\0\0\0\1", {"track": 1, "first": 0, "width": 0, "height": 8,
                                   "quality": 50, "shape": 3, "data": ""})
    assert "error" in line and store.bad == 1
    assert not list((tmp_path / "review").glob("*.jpg"))
