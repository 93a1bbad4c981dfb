"""Source spec parsing and timestamp pairing (pure)."""

from __future__ import annotations

import pytest

from trapflow.errors import ConfigError
from trapflow.sources.spec import parse_source_spec, split_gst
from trapflow.sources.sync import StereoSync, default_tolerance_ns

GST_L = "v4l2src device=/dev/video0 ! video/x-raw,width=640,height=480 ! videoconvert ! appsink"
GST_R = "v4l2src device=/dev/video1 ! video/x-raw,width=640,height=480 ! videoconvert ! appsink"


@pytest.mark.parametrize(
    ("text", "expected", "error"),
    [
        ("synthetic", ("synthetic", ""), None),
        ("video:a.mp4,b.mp4", ("video", "a.mp4,b.mp4"), None),
        ("video:sbs.mp4", ("video", "sbs.mp4"), None),
        ("images:/data/kitti/00", ("images", "/data/kitti/00"), None),
        ("v4l2:/dev/video0,/dev/video2", ("v4l2", "/dev/video0,/dev/video2"), None),
        ("picamera2:0,1", ("picamera2", "0,1"), None),
        ("replay:run.mcap", ("replay", "run.mcap"), None),
        (f"gst:{GST_L},{GST_R}", ("gst", f"{GST_L},{GST_R}"), None),
        ("VIDEO:x.avi", ("video", "x.avi"), None),
        ("webcam:0", None, "unknown kind 'webcam'"),
        ("video", None, "video needs arguments"),
        ("video:", None, "video needs arguments"),
        ("video:a.mp4,", None, "two comma-separated parts"),
        ("v4l2:/dev/video0", None, "two comma-separated parts"),
        ("v4l2:a,b,c", None, "got 3"),
        ("picamera2:0,left", None, "camera numbers, got 'left'"),
        ("synthetic:abc", None, "takes no arguments"),
    ],
)
def test_parse_source_spec(text: str, expected: tuple[str, str] | None, error: str | None) -> None:
    if error is None:
        assert parse_source_spec(text) == expected
    else:
        with pytest.raises(ConfigError, match=error):
            parse_source_spec(text)


def test_split_gst_keeps_caps_commas() -> None:
    assert split_gst(f"{GST_L},{GST_R}") == (GST_L, GST_R)
    assert split_gst("a ! appsink,b ! appsink") == ("a ! appsink", "b ! appsink")


def test_sync_pairs_within_tolerance_and_counts_drops() -> None:
    period = 66_000_000
    sync: StereoSync[int] = StereoSync(default_tolerance_ns(15.0))
    lefts = [i * period for i in range(10)]
    # Right camera runs 5 ms late and misses frame 4; an extra stray right frame at 4.5 periods.
    rights = [i * period + 5_000_000 for i in range(10) if i != 4]
    rights.insert(4, int(4.5 * period) + 40_000_000)
    pairs = []
    for t in sorted([(t, "L", i) for i, t in enumerate(lefts)] +
                    [(t, "R", i) for i, t in enumerate(rights)]):
        if t[1] == "L":
            sync.push_left(t[0], t[2])
        else:
            sync.push_right(t[0], t[2])
        while (p := sync.pop()) is not None:
            pairs.append(p)
    sync.flush()
    matched_left = [p[1] for p in pairs]
    assert 4 not in matched_left and len(pairs) == 9
    assert all(abs(tl - tr) <= sync.tolerance_ns for tl, _, tr, _ in pairs)
    assert sync.stats.pairs == 9
    assert sync.stats.dropped_left == 1 and sync.stats.dropped_right == 1
    assert sync.stats.skew_max_ns == 5_000_000
    assert sync.stats.skew_mean_ns == pytest.approx(5_000_000)


def test_sync_prefers_closer_partner_already_waiting() -> None:
    sync: StereoSync[str] = StereoSync(tolerance_ns=30)
    sync.push_left(100, "l0")
    sync.push_right(80, "r0")
    sync.push_right(101, "r1")
    assert sync.pop() == (100, "l0", 101, "r1")
    assert sync.stats.dropped_right == 1


def test_sync_bounds_pending_frames() -> None:
    sync: StereoSync[int] = StereoSync(tolerance_ns=10, max_pending=3)
    for i in range(10):
        sync.push_left(i * 100, i)
    assert sync.pop() is None
    assert sync.stats.dropped_left == 7


def test_sync_rejects_negative_tolerance() -> None:
    with pytest.raises(ValueError, match="tolerance must be >= 0"):
        StereoSync(tolerance_ns=-1)
