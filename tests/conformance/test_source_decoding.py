"""Finite sources on third-party images: every real JPEG and PNG of the kit (several
encoders) decodes to exactly what OpenCV's own reader gives, and every cut-short copy is
caught, where OpenCV's reader accepts most of them silently (issue 12, item 2)."""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.conformance.conftest import kit_path
from tests.conftest import Pipeline, write_config
from trapflow.sources.base import SkipPair
from trapflow.sources.decode import decode_bgr

CUTS = (0.25, 0.5, 0.75, 0.99)  # fractions of the file kept
STEREO = ("01_stereo_checkerboard_opencv", "images")


def kit_images(root: Path) -> list[Path]:
    files = sorted(p for p in root.rglob("*") if p.suffix.lower() in (".jpg", ".png"))
    if not files:
        pytest.skip(f"real-data kit at {root} has no JPEG or PNG files")
    return files


def test_every_real_image_decodes_as_opencv_reads_it(realdata: Path) -> None:
    files = kit_images(realdata)
    assert len(files) >= 100
    for path in files:
        ref = cv2.imread(str(path), cv2.IMREAD_COLOR)
        assert ref is not None, path
        out = decode_bgr(path.read_bytes(), str(path))  # no false alarm on a whole file
        assert out.shape == ref.shape and np.array_equal(out, ref), path


def test_every_cut_real_image_is_caught(realdata: Path, tmp_path: Path) -> None:
    files = kit_images(realdata)
    silently_read = caught = 0
    for path in files:
        data = path.read_bytes()
        for frac in CUTS:
            cut = tmp_path / f"cut{path.suffix}"
            cut.write_bytes(data[: int(len(data) * frac)])
            if cv2.imread(str(cut), cv2.IMREAD_COLOR) is not None:
                silently_read += 1  # the old path: a partly grey image, no error
            with pytest.raises(SkipPair) as info:
                decode_bgr(cut.read_bytes(), str(cut))
            assert info.value.kind == "truncated", (path, frac, info.value)
            caught += 1
    assert caught == len(files) * len(CUTS)
    print(f"cut copies: {caught}, caught {caught}, read silently by cv2.imread {silently_read}")
    assert silently_read > 0  # the reason for the check: OpenCV alone lets them through


def link_pairs(src: Path, dst: Path) -> list[int]:
    """left/NN.jpg and right/NN.jpg linked to the kit's files (read in place, not copied)."""
    numbers = sorted(int(p.stem[4:]) for p in src.glob("left*.jpg"))
    for side in ("left", "right"):
        (dst / side).mkdir(parents=True)
        for n in numbers:
            os.symlink(src / f"{side}{n:02d}.jpg", dst / side / f"{n:02d}.jpg")
    return numbers


@pytest.mark.timeout(120)
def test_real_stereo_folder_with_a_cut_file_ends_and_counts_it(
    realdata: Path, spawn, run_dir: Path
) -> None:
    """OpenCV's 13 real stereo pairs as an images folder, one left image replaced by a
    copy cut to half: the run ends by itself, the pair is counted as truncated, and every
    other pair reaches the worker with the pixels OpenCV's reader gives for its files."""
    src = kit_path(realdata, *STEREO)
    d = run_dir.parent / "pairs"
    numbers = link_pairs(src, d)
    victim = numbers[4]
    (d / "left" / f"{victim:02d}.jpg").unlink()
    data = (src / f"left{victim:02d}.jpg").read_bytes()
    (d / "left" / f"{victim:02d}.jpg").write_bytes(data[: len(data) // 2])
    cfg = write_config(run_dir.parent / "c.yaml",
                       {"pools": {"every": {"plugin": "digest", "policy": "ordered:64"}}})
    p: Pipeline = spawn(["--config", str(cfg), "--workers", "every=1", "--source",
                         f"images:{d}", "--size", "640x480", "--encoding", "raw",
                         "--rate", "20"], run_dir)
    code, _, err = p.wait(90)
    assert code == 0, err
    ledger = json.loads((run_dir / "ledger.json").read_text())
    assert ledger["capture_failures"] == {"truncated": 1}
    good = [n for n in numbers if n != victim]
    assert ledger["produced"] == len(good) == ledger["pools"]["every"]["processed"]
    expected = []
    for n in good:
        h = hashlib.sha1(cv2.imread(str(src / f"left{n:02d}.jpg"), cv2.IMREAD_COLOR).tobytes())
        h.update(cv2.imread(str(src / f"right{n:02d}.jpg"), cv2.IMREAD_COLOR).tobytes())
        expected.append(h.hexdigest()[:16])
    assert [r["digest"]["sha1"] for r in p.results()] == expected
