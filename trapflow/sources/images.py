"""Image folder sources: DIR/left + DIR/right, or the KITTI odometry layout with calib.txt.

Pairs by file name when both sides use the same names, else by sorted index; times come
from times.txt (seconds, one line per pair) when present, else from the configured rate.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np

from trapflow.calibration.camera import StereoRig
from trapflow.calibration.rig_files import read_kitti_calib as read_rig_kitti
from trapflow.config.schema import SourceConfig
from trapflow.errors import ConfigError
from trapflow.sources.base import Frames, Geometry, SkipPair, Source, SourceError
from trapflow.sources.decode import decode_bgr, same_size

log = logging.getLogger(__name__)

IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".ppm", ".pgm"}
LAYOUTS = (("left", "right"), ("image_0", "image_1"), ("image_2", "image_3"))
GEOMETRY_TRIES = 10  # left images tried for the frame size before giving up


def list_images(folder: Path) -> list[Path]:
    """Image files in a folder, sorted by name."""
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)


def read_times(path: Path) -> list[int]:
    """times.txt (one time in seconds per line) as nanoseconds; SourceError names a bad line."""
    out = []
    for n, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        if not line.strip():
            continue
        try:
            out.append(int(round(float(line.split()[0]) * 1e9)))
        except ValueError:
            raise SourceError(f"images: {path} line {n}: expected seconds, got {line!r}") from None
    return out


def read_kitti_calib(path: Path, width: int, height: int) -> StereoRig:
    """The rig from a KITTI calib.txt; SourceError says what is wrong."""
    try:
        return read_rig_kitti(path, (width, height))
    except ConfigError as exc:
        raise SourceError(f"images: {exc}") from None


def pair_files(left: list[Path], right: list[Path]) -> list[tuple[Path, Path]]:
    """Pair by identical names when the sides share them, else by sorted position."""
    rnames = {p.name: p for p in right}
    common = [p for p in left if p.name in rnames]
    if common and len(common) >= min(len(left), len(right)) // 2:
        return [(p, rnames[p.name]) for p in common]
    if len(left) != len(right):
        log.warning("images: %d left and %d right images; pairing the first %d by position",
                    len(left), len(right), min(len(left), len(right)))
    n = min(len(left), len(right))
    return list(zip(left[:n], right[:n], strict=True))


class ImagesSource(Source):
    """`images:DIR` with left/ and right/ (or KITTI image_0/ image_1/, times.txt, calib.txt)."""

    finite = True

    def __init__(self, cfg: SourceConfig, rig: StereoRig) -> None:
        super().__init__(rig)
        self.cfg = cfg
        self.loop = cfg.loop
        self.finite = not cfg.loop
        self.root = Path(cfg.uri)
        self.pairs: list[tuple[Path, Path]] = []
        self.times: list[int] | None = None
        self._i = 0
        self._index = 0
        self._t0 = 0
        self._period_ns = int(1e9 / cfg.rate_hz)

    def _scan(self) -> list[tuple[Path, Path]]:
        """The folder's image pairs; SourceError when it has none or no known layout."""
        root = self.root
        if not root.is_dir():
            raise SourceError(f"images: folder not found: {root}")
        sides = next(((root / a, root / b) for a, b in LAYOUTS
                      if (root / a).is_dir() and (root / b).is_dir()), None)
        if sides is None:
            names = " or ".join(f"{a}/ and {b}/" for a, b in LAYOUTS)
            raise SourceError(f"images: {root} has no {names} subfolders")
        pairs = pair_files(list_images(sides[0]), list_images(sides[1]))
        if not pairs:
            raise SourceError(f"images: no images in {sides[0]} and {sides[1]}")
        return pairs

    def geometry(self) -> Geometry:
        """The first left image's size, and calib.txt's rig at that size when there is one."""
        pairs = self.pairs or self._scan()
        first = None
        for left, _right in pairs[:GEOMETRY_TRIES]:  # an unreadable file is not the geometry
            try:
                first = self._load(left)
            except SkipPair:
                continue
            break
        if first is None:
            raise SourceError(f"images: none of the first {min(len(pairs), GEOMETRY_TRIES)} "
                              f"left images in {self.root} can be read")
        size = (first.shape[1], first.shape[0])
        where = f"images in {self.root}"
        calib = self.root / "calib.txt"
        if calib.is_file():
            return Geometry(size=size, rig=read_kitti_calib(calib, *size),
                            origin=f"{calib}", where=where)
        return Geometry(size=size, where=where)

    def open(self) -> None:
        root = self.root
        self.pairs = self._scan()
        times_path = root / "times.txt"
        if times_path.is_file():
            self.times = read_times(times_path)
            if len(self.times) < len(self.pairs):
                raise SourceError(f"images: {times_path} has {len(self.times)} times "
                                  f"for {len(self.pairs)} pairs")
        geometry = self.geometry()
        if geometry.rig is not None:
            self.rig = geometry.rig
            log.info("images: rig from %s: %s", geometry.origin, self.rig.describe())
        self._t0 = time.monotonic_ns()

    def _load(self, path: Path) -> np.ndarray:
        """One image, decoded strictly; SkipPair when empty, cut short or not an image."""
        try:
            data = path.read_bytes()
        except OSError as exc:
            if not path.parent.is_dir():  # the disk or folder is gone, not one file
                raise SourceError(f"images: folder {path.parent} not found "
                                  "(disk removed or folder moved?)") from None
            raise SkipPair("unreadable", f"images: cannot read {path}: {exc.strerror}") from None
        return decode_bgr(data, f"images: {path}")

    def _time(self, i: int) -> int:
        if self.times is None:
            return self._index * self._period_ns
        lap = self._index // len(self.pairs)  # loops continue after the last time
        span = self.times[len(self.pairs) - 1] - self.times[0] + self._period_ns
        return lap * span + self.times[i] - self.times[0]

    def read(self) -> Frames | None:
        if not self.pairs:
            raise SourceError("images: read() before open()")
        if self._i >= len(self.pairs):
            if not self.loop:
                return None
            self._i = 0
        lp, rp = self.pairs[self._i]
        t = self._t0 + self._time(self._i)
        # Past this pair before reading it: an unreadable one is skipped, never retried.
        self._i += 1
        self._index += 1
        left, right = self._load(lp), self._load(rp)
        same_size(left, right,
                  f"images: {lp.parent.name}/{lp.name} and {rp.parent.name}/{rp.name}")
        return Frames(left=left, right=right, t_left_ns=t, t_right_ns=t)
