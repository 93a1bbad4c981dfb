"""The pure core of `trapflow process`: inputs found in paths, chunks cut from pair counts,
VO chunk boundaries stitched, and per-input ledgers merged. No Dask, no files written.

A chunk is a half-open range [start, end) of a finite source's read positions (each
position is one read(): a pair, or a pair the source skips). Stateless pools share one
chunk grid; each ordered pool (policy `ordered`, PoolConfig.ordered: visual odometry, or
any plugin that keeps state from pair to pair) has its own, time-ordered grid whose chunks
start `overlap` positions early so each re-initialises on pairs its predecessor also saw.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Collection, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from trapflow.errors import ConfigError

#: file suffixes read as recordings (trapflow MCAP, ROS 2 bags) and as videos
RECORDING_SUFFIXES = (".mcap", ".db3")
VIDEO_SUFFIXES = (".mp4", ".avi", ".mkv", ".mov", ".m4v", ".webm")
IMAGE_LAYOUTS = (("left", "right"), ("image_0", "image_1"), ("image_2", "image_3"))
WHOLE = 0  # a chunk size of 0: the whole sequence in one chunk


@dataclass(frozen=True)
class Input:
    """One finite source: its name under --out, and the source kind and uri it opens."""

    name: str
    kind: str
    uri: str


@dataclass(frozen=True)
class Chunk:
    """Read positions [start, end) of one input for some pools; `first` is where its
    results begin (start + overlap for a VO chunk that re-initialises early); `ordered`: a
    chunk of an ordered pool's time-ordered grid."""

    input: str
    pools: tuple[str, ...]
    start: int
    end: int
    first: int
    ordered: bool = False

    @property
    def key(self) -> str:
        """A file-name-safe id, unique within an input."""
        return f"{'+'.join(self.pools)}-{self.first:08d}-{self.end:08d}"


def _kind_of(path: Path) -> str | None:
    if path.is_file():
        if path.suffix.lower() in RECORDING_SUFFIXES or path.name.endswith(".mcap.part"):
            return "replay"
        if path.suffix.lower() in VIDEO_SUFFIXES:
            return "video"
        return None
    if path.is_dir():
        if (path / "metadata.yaml").is_file():  # a ROS 2 bag folder
            return "replay"
        if any((path / a).is_dir() and (path / b).is_dir() for a, b in IMAGE_LAYOUTS):
            return "images"
    return None


def find_inputs(args: Sequence[str]) -> list[Input]:
    """Inputs from command-line arguments: a recording, bag, image folder, KITTI folder or
    video; `KIND:ARGS` (e.g. video:l.mp4,r.mp4); or a folder tree searched for them.

    ConfigError names an argument that is none of these, or a tree with no input in it.
    """
    found: list[tuple[Path | None, str, str, str]] = []  # (root, label, kind, uri)
    for arg in args:
        path = Path(arg)
        kind = _kind_of(path)
        if kind is not None:
            found.append((None, path.name or arg, kind, str(path)))
            continue
        if path.is_dir():
            before = len(found)
            for sub in sorted(p for p in path.rglob("*") if _kind_of(p) is not None):
                if any(_kind_of(parent) is not None for parent in sub.parents
                       if path in parent.parents):
                    continue  # inside an input already found (an image folder's left/)
                rel = sub.relative_to(path)
                found.append((path, f"{path.name}/{rel}", _kind_of(sub) or "", str(sub)))
            if len(found) == before:
                raise ConfigError(
                    f"input {arg}: a folder with no input in it; expected recordings "
                    f"({', '.join(RECORDING_SUFFIXES)}), ROS 2 bag folders, image folders "
                    f"(left/ and right/, or image_0/ and image_1/) or videos "
                    f"({', '.join(VIDEO_SUFFIXES)}) somewhere below it")
            continue
        from trapflow.sources.spec import parse_source_spec

        if ":" in arg and not path.exists():
            kind, uri = parse_source_spec(arg)
            if kind in ("v4l2", "picamera2", "gst", "synthetic"):
                raise ConfigError(f"input {arg}: a {kind} source never ends; `process` takes "
                                  "finite inputs (recordings, bags, image folders, videos)")
            found.append((None, Path(uri.split(",")[0]).name, kind, uri))
            continue
        raise ConfigError(f"input {arg}: not found or not a known input; expected a recording "
                          f"({', '.join(RECORDING_SUFFIXES)}), a ROS 2 bag folder, an image "
                          f"folder, a video, KIND:ARGS, or a folder tree of them")
    return _named(found)


def _named(found: list[tuple[Path | None, str, str, str]]) -> list[Input]:
    """Unique, file-name-safe names ('a/b' -> 'a__b'; a repeated name gets '-2', '-3')."""
    out: list[Input] = []
    seen: dict[str, int] = {}
    for _root, label, kind, uri in found:
        name = label.replace("/", "__").replace(":", "_") or "input"
        seen[name] = seen.get(name, 0) + 1
        if seen[name] > 1:
            name = f"{name}-{seen[name]}"
        out.append(Input(name=name, kind=kind, uri=uri))
    return out


def cut(n: int, size: int) -> list[tuple[int, int]]:
    """[start, end) ranges covering 0..n in pieces of `size` (WHOLE: one piece)."""
    if n <= 0:
        return []
    if size == WHOLE or size >= n:
        return [(0, n)]
    return [(a, min(a + size, n)) for a in range(0, n, size)]


def plan_chunks(name: str, n: int, pools: Sequence[str], size: int, vo_size: int,
                vo_overlap: int, ordered: Collection[str] = ()) -> list[Chunk]:
    """Every chunk of one input of n read positions, stateless pools first, then each of
    the `ordered` pools (those whose config says PoolConfig.ordered) in time order. An
    ordered chunk after the first starts `vo_overlap` positions early."""
    stateless = tuple(p for p in pools if p not in ordered)
    chunks = [Chunk(name, stateless, a, b, a) for a, b in cut(n, size)] if stateless else []
    for pool in (p for p in pools if p in ordered):
        for a, b in cut(n, vo_size):
            chunks.append(Chunk(name, (pool,), max(0, a - vo_overlap), b, a, ordered=True))
    return chunks


def fingerprint(data: Any) -> str:
    """A short stable hash of JSON-able data: a finished chunk counts only for the same plan."""
    text = json.dumps(data, sort_keys=True, default=str).encode()
    return hashlib.sha256(text).hexdigest()[:16]


# --- VO chunk boundaries -------------------------------------------------------------------


def pose44(rows: Iterable[Iterable[float]]) -> np.ndarray:
    """A 4x4 pose from the 3x4 rows of a result's `pose`."""
    m = np.eye(4)
    m[:3, :4] = np.asarray([list(r) for r in rows], dtype=float)
    return m


@dataclass(frozen=True)
class Boundary:
    """Where one VO chunk hands over to the next, and what the re-initialisation cost.

    The cost compares the pose of the last overlapping pair as the predecessor
    integrated it with the same pose from the new chunk, chained onto the predecessor at
    the new chunk's first pair: the drift that the re-initialisation adds.
    """

    at: int  # first read position the new chunk reports
    overlap: int
    compared_seq: int | None  # the pair both chunks posed (None: nothing to compare)
    translation_m: float | None
    rotation_deg: float | None

    def as_dict(self) -> dict[str, Any]:
        return {"at": self.at, "overlap": self.overlap, "compared_seq": self.compared_seq,
                "drift_translation_m": self.translation_m, "drift_rotation_deg": self.rotation_deg}


def _angle_deg(r: np.ndarray) -> float:
    c = (np.trace(r) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


@dataclass
class Stitcher:
    """Chains the poses of successive VO chunks into one trajectory and measures each
    boundary. Feed chunks in time order: their `stereo_vo` lines (all of them, overlap
    included); returns the lines to keep, poses rewritten in the first chunk's frame."""

    decimals: int = 3
    boundaries: list[Boundary] = field(default_factory=list)
    _poses: dict[int, np.ndarray] = field(default_factory=dict)  # seq -> world pose so far

    def add(self, chunk: Chunk, lines: list[dict[str, Any]]) -> list[dict[str, Any]]:
        own = {ln["stereo_vo"]["seq"]: pose44(ln["stereo_vo"]["pose"]) for ln in lines
               if "pose" in ln["stereo_vo"]}
        anchor: np.ndarray | None = None
        if chunk.start in own and chunk.start in self._poses:
            # The chunk's frame is its first pair's pose; that pair's place in the world
            # is what the predecessor integrated for it.
            anchor = self._poses[chunk.start] @ np.linalg.inv(own[chunk.start])
        if chunk.start > 0 or chunk.first > 0:
            self.boundaries.append(self._measure(chunk, own, anchor))
        first_chunk = not self._poses
        if anchor is None:
            anchor = np.eye(4) if first_chunk else self._poses[max(self._poses)]
        kept = []
        for ln in lines:
            body = ln["stereo_vo"]
            if body["seq"] < chunk.first:
                continue
            if "pose" in body:
                world = anchor @ own[body["seq"]]
                self._poses[body["seq"]] = world
                if first_chunk:  # already in the trajectory's frame: the lines as they came
                    kept.append(ln)
                    continue
                body = {**body, "pose": [[round(float(v), self.decimals) for v in row]
                                         for row in world[:3, :4]]}
            kept.append({"stereo_vo": body})
        return kept

    def _measure(self, chunk: Chunk, own: dict[int, np.ndarray],
                 anchor: np.ndarray | None) -> Boundary:
        overlap = chunk.first - chunk.start
        last = chunk.first - 1
        if anchor is None or overlap < 2 or last not in own or last not in self._poses:
            return Boundary(chunk.first, overlap, None, None, None)
        mine = anchor @ own[last]
        theirs = self._poses[last]
        delta = np.linalg.inv(theirs) @ mine
        return Boundary(chunk.first, overlap, last, float(np.linalg.norm(delta[:3, 3])),
                        _angle_deg(delta[:3, :3]))
