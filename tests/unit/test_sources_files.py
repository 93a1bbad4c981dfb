"""Video and image-folder sources on real files written here (AVI, PNG, KITTI layout)."""

from __future__ import annotations

import re
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.builders import drain, drain_skipping
from trapflow.calibration.camera import StereoRig
from trapflow.config.schema import SourceConfig
from trapflow.sources.base import SkipPair, Source, SourceError
from trapflow.sources.factory import open_source

RIG = StereoRig.from_fov(64, 48, 70.0, 0.12)
W, H = 64, 48


def frame(i: int, side: int) -> np.ndarray:
    """A frame whose brightness encodes its index and side (survives lossy codecs)."""
    img = np.full((H, W, 3), 10 + 20 * i + (100 if side else 0), dtype=np.uint8)
    return img


def index_of(img: np.ndarray, side: int) -> int:
    return int(round((float(img.mean()) - 10 - (100 if side else 0)) / 20))


def write_video(path: Path, frames: list[np.ndarray], fps: float = 10.0) -> None:
    h, w = frames[0].shape[:2]
    out = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"MJPG"), fps, (w, h))
    assert out.isOpened()
    for f in frames:
        out.write(f)
    out.release()


def make(kind: str, uri: str, loop: bool = False) -> Source:
    return open_source(SourceConfig(kind=kind, uri=uri, loop=loop, rate_hz=10.0), RIG)


def test_two_video_files_pair_by_index(tmp_path: Path) -> None:
    write_video(tmp_path / "l.avi", [frame(i, 0) for i in range(5)])
    write_video(tmp_path / "r.avi", [frame(i, 1) for i in range(5)])
    got = drain(make("video", f"{tmp_path / 'l.avi'},{tmp_path / 'r.avi'}"))
    assert [index_of(f.left, 0) for f in got] == list(range(5))
    assert [index_of(f.right, 1) for f in got] == list(range(5))
    times = [f.t_left_ns for f in got]
    assert np.diff(times).tolist() == [100_000_000] * 4
    assert all(f.left.dtype == np.uint8 and f.left.shape == (H, W, 3) for f in got)


def test_side_by_side_video_splits_halves_and_loops(tmp_path: Path) -> None:
    write_video(tmp_path / "sbs.avi", [np.hstack([frame(i, 0), frame(i, 1)]) for i in range(3)])
    src = make("video", str(tmp_path / "sbs.avi"), loop=True)
    assert not src.finite
    got = drain(src, limit=7)
    assert [index_of(f.left, 0) for f in got] == [0, 1, 2, 0, 1, 2, 0]
    assert [index_of(f.right, 1) for f in got] == [0, 1, 2, 0, 1, 2, 0]
    assert np.all(np.diff([f.t_left_ns for f in got]) > 0)


def write_pngs(folder: Path, side: int, n: int, gray: bool = False) -> None:
    folder.mkdir(parents=True)
    for i in range(n):
        img = frame(i, side)
        cv2.imwrite(str(folder / f"{i:06d}.png"), img[:, :, 0] if gray else img)


def test_image_folders_left_right(tmp_path: Path) -> None:
    write_pngs(tmp_path / "left", 0, 4)
    write_pngs(tmp_path / "right", 1, 4)
    src = make("images", str(tmp_path))
    got = drain(src)
    assert src.finite
    assert [index_of(f.left, 0) for f in got] == [0, 1, 2, 3]
    assert [index_of(f.right, 1) for f in got] == [0, 1, 2, 3]


def test_kitti_layout_times_and_calib(tmp_path: Path) -> None:
    write_pngs(tmp_path / "image_0", 0, 3, gray=True)
    write_pngs(tmp_path / "image_1", 1, 3, gray=True)
    (tmp_path / "times.txt").write_text("0.000000e+00\n1.036224e-01\n2.072000e-01\n")
    fx, cx, cy, base = 718.856, 607.1928, 185.2157, 0.5371657
    p0 = f"{fx} 0 {cx} 0 0 {fx} {cy} 0 0 0 1 0"
    p1 = f"{fx} 0 {cx} {-fx * base} 0 {fx} {cy} 0 0 0 1 0"
    (tmp_path / "calib.txt").write_text(f"P0: {p0}\nP1: {p1}\nP2: {p0}\nP3: {p1}\n")
    src = make("images", str(tmp_path))
    got = drain(src)
    assert [index_of(f.left, 0) for f in got] == [0, 1, 2]
    assert got[0].left.shape == (H, W, 3)  # grey KITTI images become BGR
    dt = [b.t_left_ns - got[0].t_left_ns for b in got]
    assert dt == [0, 103_622_400, 207_200_000]
    assert src.rig.fx == pytest.approx(fx) and src.rig.cx == pytest.approx(cx)
    assert src.rig.baseline_m == pytest.approx(base)
    assert (src.rig.width, src.rig.height) == (W, H)


@pytest.mark.parametrize(
    ("kind", "setup", "error"),
    [
        ("video", lambda d: str(d / "missing.avi"), "video: file not found"),
        ("video", lambda d: (d / "bad.avi").write_bytes(b"not a video" * 50) and str(d / "bad.avi"),
         "video: cannot decode|video: no frame could be decoded"),
        ("images", lambda d: str(d / "nowhere"), "images: folder not found"),
        ("images", lambda d: str(d), "has no left/ and right/"),
        ("images", lambda d: ((d / "left").mkdir(), (d / "right").mkdir(), str(d))[-1],
         "images: no images in"),
    ],
)
def test_bad_inputs_fail_with_one_clear_reason(
    tmp_path: Path, kind: str, setup: Callable[[Path], str], error: str
) -> None:
    src = make(kind, setup(tmp_path))
    with pytest.raises(SourceError, match=error):
        src.open()
        src.read()
    src.close()


def test_unreadable_image_names_the_file_and_the_folder_goes_on(tmp_path: Path) -> None:
    """Regression (issue 12, item 2): one unreadable file was retried forever; now read()
    raises SkipPair once for it, naming the file, and the next read() is the next pair."""
    write_pngs(tmp_path / "left", 0, 3)
    write_pngs(tmp_path / "right", 1, 3)
    (tmp_path / "left" / "000001.png").write_bytes(b"garbage")
    src = make("images", str(tmp_path))
    src.open()
    first = src.read()
    assert first is not None and index_of(first.left, 0) == 0
    with pytest.raises(SkipPair, match="no image decoder accepts") as info:
        src.read()
    assert "000001.png" in str(info.value) and info.value.kind == "unreadable"
    third = src.read()
    assert third is not None and index_of(third.left, 0) == 2
    assert src.read() is None
    src.close()


def _bad_left(kind: str) -> Callable[[Path], None]:
    def damage(folder: Path) -> None:
        target = folder / "left" / "000002.png"
        if kind == "empty":
            target.write_bytes(b"")
        elif kind == "garbage":
            target.write_bytes(b"\x89PNG but not really" * 4)
        elif kind == "cut":
            target.write_bytes(target.read_bytes()[:-30])
        elif kind == "size":
            cv2.imwrite(str(folder / "right" / "000002.png"), np.zeros((H // 2, W, 3), np.uint8))
        elif kind == "missing":
            target.unlink()
            target.mkdir()  # a name that cannot be read as a file
    return damage


@pytest.mark.parametrize(
    ("damage", "kind", "error"),
    [
        ("empty", "unreadable", "000002.png: empty"),
        ("garbage", "unreadable", "000002.png: .* no image decoder accepts"),
        ("cut", "truncated", "000002.png: PNG of .* has no IEND chunk"),
        ("size", "size", "left/000002.png and right/000002.png: left is 64x48, right is 64x24"),
        ("missing", "unreadable", "cannot read .*000002.png"),
    ],
)
def test_each_bad_pair_is_skipped_once_with_its_reason(
    tmp_path: Path, damage: str, kind: str, error: str
) -> None:
    write_pngs(tmp_path / "left", 0, 5)
    write_pngs(tmp_path / "right", 1, 5)
    _bad_left(damage)(tmp_path)
    got, skipped = drain_skipping(make("images", str(tmp_path)), 10)
    assert [index_of(f.left, 0) for f in got] == [0, 1, 3, 4]
    assert len(skipped) == 1 and skipped[0].kind == kind
    assert re.search(error, str(skipped[0])), str(skipped[0])


def test_a_folder_that_disappears_is_a_source_error_not_a_skipped_pair(tmp_path: Path) -> None:
    """A removed disk is not one bad file: the source cannot go on (a finite run ends with
    status 1 saying so; a looping one is retried with back-off like a camera)."""
    write_pngs(tmp_path / "d" / "left", 0, 3)
    write_pngs(tmp_path / "d" / "right", 1, 3)
    src = make("images", str(tmp_path / "d"))
    src.open()
    assert src.read() is not None
    (tmp_path / "d").rename(tmp_path / "gone")
    with pytest.raises(SourceError, match="images: folder .*left not found") as info:
        src.read()
    assert not isinstance(info.value, SkipPair)
    src.close()
