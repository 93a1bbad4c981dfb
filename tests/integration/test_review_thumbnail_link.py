"""A queued review item reaches the surface as a thumbnail: a detector worker's crop of a
track's box (pools/pair_path.crop_views) rides its result to the normalizer's observer,
the track ends in the review band, its crop is fitted to the default budget and queued in
the outbox as `thumb` records, the box's sender carries them over the simulated 300 bit/s
link with 5 % loss, and `trapflow surface` writes review/SESSION-TRACK.jpg beside its
output, which decodes to the thumbnail's size."""

from __future__ import annotations

import logging
import subprocess
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from tests import builders
from tests.conftest import modem_cli, run_sender_until
from tests.integration.test_modem_link import lines_of, start_sim, stop
from trapflow.config.modem import ModemConfig, OutboxConfig
from trapflow.config.schema import ObserveConfig, ReviewConfig, from_data
from trapflow.modem import thumb
from trapflow.modem.outbox import Outbox
from trapflow.normalizer.node import NormalizerNode
from trapflow.normalizer.result_json import normalize
from trapflow.plugin import Pair
from trapflow.pools.pair_path import ViewSpec, crop_views
from trapflow.runtime.ratelog import RateLimitedLog
from trapflow.tracking.stage import Observer
from trapflow.wire import messages


def _frame(x: int) -> np.ndarray:
    """A sandy floor with a red crab at x."""
    rng = np.random.default_rng(x)
    img = cv2.GaussianBlur(rng.integers(60, 200, (360, 480, 3), dtype=np.uint8), (0, 0), 2)
    cv2.ellipse(img, (x, 180), (50, 30), 0, 0, 360, (30, 40, 200), -1)
    return img


def _queued_review() -> dict:
    """Six pairs of one crab at 0.55 (in the review band) through the worker's crop, the
    wire and the normalizer's observer; the track's review line with its crop."""
    observer = Observer(ObserveConfig(), review=ReviewConfig(audit=0.0), pool="mono")
    reviews = []
    for i in range(6):
        x = 150 + 4 * i
        frame = _frame(x)
        box = (float(x - 55), 145.0, float(x + 55), 215.0)
        body = messages.MonoIR(detections=[messages.Detection(label="crab", confidence=0.55,
                                                              box=box)])
        pair = Pair(header=builders.pair_header(i, 480, 360), left=frame, right=frame)
        body = crop_views(body, pair, ViewSpec(min_confidence=0.5, crop_px=256))
        res = messages.decode_result(messages.encode(builders.result(body, seq=i)))
        items = [obj["mono_ir"] for obj in normalize(res)]
        got = observer.feed(int(i * 0.2e9), items, res.t_wall_ns)
        NormalizerNode._offer_views(observer, res, items)
        reviews += got.reviews
    reviews += observer.finish().reviews
    assert len(reviews) == 1 and "jpeg" in reviews[0]["review"]
    return dict(reviews[0]["review"])


@pytest.mark.timeout(90)
def test_a_queued_tracks_thumbnail_reaches_the_surface_and_decodes(
        tmp_path: Path, started_procs: list[subprocess.Popen[bytes]]) -> None:
    review = _queued_review()
    budget = ReviewConfig().thumbnail_bytes
    records = thumb.records(review["track"], review["jpeg"], budget)
    assert len(records) >= 2 and thumb.cost(records) <= budget
    box = Outbox(tmp_path / "outbox.sqlite", OutboxConfig())
    box.append_many(records)

    start_sim(tmp_path, started_procs, "--bit-rate", "300", "--latency", "0.3",
              "--loss", "0.05", "--seed", "3")
    out = tmp_path / "surface.jsonl"
    surface = modem_cli("surface", str(tmp_path / "b"), "-o", str(out))
    started_procs.append(surface)
    cfg = ModemConfig(enabled=True, port=str(tmp_path / "a"), bit_rate=300.0,
                      ack_timeout_s=1.5, reopen_interval_s=0.5)
    elapsed, stats = run_sender_until(tmp_path / "outbox.sqlite", cfg,
                                      lambda: box.counts()[2] == 0, 70,
                                      "the thumbnail to be acknowledged")
    surface_stats = stop(surface)
    box.close()

    lines = [rec["thumb"] for rec in lines_of(out) if "thumb" in rec]
    assert len(lines) == len(records)  # each packet once
    assert sorted(line["first"] for line in lines) == sorted(
        r["thumb"]["first"] for r in records)
    last = lines[-1]
    assert last["segments"] == last["of"] and "data" not in last
    path = out.parent / last["file"]
    assert path.parent.name == "review" and path.name.endswith(f"-{review['track']}.jpg")
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    first = records[0]["thumb"]
    assert img is not None and img.shape == (first["height"], first["width"], 3)
    # the picture is the crop's: close to the crop shrunk to the thumbnail's size
    crop = cv2.imdecode(np.frombuffer(review["jpeg"], np.uint8), cv2.IMREAD_COLOR)
    ref = cv2.resize(crop, (first["width"], first["height"]), interpolation=cv2.INTER_AREA)
    assert np.abs(img.astype(int) - ref.astype(int)).mean() < 25
    assert surface_stats["thumbnails"] == len(records)
    print(f"thumbnail {first['width']}x{first['height']} q{first['quality']}: "
          f"{thumb.cost(records)} bytes in {len(records)} packets; sender sent "
          f"{stats['bytes']} bytes ({stats['retransmits']} retransmits) in {elapsed:.1f} s "
          f"at 300 bit/s with 5 % loss")


def test_the_normalizer_writes_the_crop_the_line_and_the_thumbnail_records(
        tmp_path: Path) -> None:
    """The normalizer's own step for a queued track (no pipeline: its writer alone)."""
    review = _queued_review()
    cfg = from_data({"modem": {"enabled": True}})
    node = NormalizerNode.__new__(NormalizerNode)  # its writer only: no sockets
    path = tmp_path / cfg.review.file
    with open(path, "ab", buffering=0) as fh:
        node.__dict__.update(
            cfg=cfg, spec=SimpleNamespace(run_dir=tmp_path), obs_files={cfg.review.file: fh},
            outbox=Outbox(tmp_path / "outbox.sqlite", OutboxConfig()), reviews=0,
            thumbnails=0, refused=0, full_now=False, disk_full={},
            ratelog=RateLimitedLog(logging.getLogger("test")))
        node._write_reviews([{"review": review}])
    line = lines_of(path)[0]["review"]
    crop = cv2.imread(str(tmp_path / line["crop"]), cv2.IMREAD_COLOR)
    assert line["crop"] == f"review/mono-{review['track']}.jpg" and crop is not None
    assert "jpeg" not in line
    sent = line["thumbnail"]
    assert sent["bytes"] <= cfg.review.thumbnail_bytes and sent["packets"] >= 2
    stored = node.outbox.read()
    assert [s.cls for s in stored] == ["thumb"] * sent["packets"]
    assert [s.record() for s in stored] == thumb.records(review["track"], review["jpeg"],
                                                         cfg.review.thumbnail_bytes)
    assert node.thumbnails == 1 and node.reviews == 1
    node.outbox.close()
