"""The pure core of `trapflow process`: inputs found in paths, chunks, VO boundary stitching,
and the command line's rejection of bad arguments (no Dask, no processes)."""

from __future__ import annotations

import json
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import cv2
import msgspec
import numpy as np
import pytest
from click.testing import CliRunner

from trapflow.batch.chunk import ChunkTask, chunk_paths, run_chunk
from trapflow.batch.plan import Chunk, Input, Stitcher, cut, find_inputs, plan_chunks
from trapflow.batch.run import ordered_pools
from trapflow.cli.main import main
from trapflow.config import schema as configmod
from trapflow.config.schema import Config
from trapflow.errors import ConfigError
from trapflow.plugin import Context, Pair, Worker
from trapflow.wire.messages import Extra


def images(root: Path, left: str = "left", right: str = "right") -> Path:
    (root / left).mkdir(parents=True)
    (root / right).mkdir(parents=True)
    return root


@pytest.mark.parametrize(("n", "size", "want"), [
    (0, 4, []),
    (3, 4, [(0, 3)]),
    (8, 4, [(0, 4), (4, 8)]),
    (9, 4, [(0, 4), (4, 8), (8, 9)]),
    (9, 0, [(0, 9)]),  # whole sequence
])
def test_cut(n: int, size: int, want: list[tuple[int, int]]) -> None:
    assert cut(n, size) == want


def test_vo_chunks_start_early_by_the_overlap_and_report_from_their_own_start() -> None:
    chunks = plan_chunks("a", 10, ("mono", "vo"), 5, 4, 2, ordered={"vo"})
    assert [(c.pools, c.start, c.first, c.end) for c in chunks] == [
        (("mono",), 0, 0, 5), (("mono",), 5, 5, 10),
        (("vo",), 0, 0, 4), (("vo",), 2, 4, 8), (("vo",), 6, 8, 10)]
    assert len({c.key for c in chunks}) == len(chunks)
    whole = plan_chunks("a", 10, ("vo",), 5, 0, 2, ordered={"vo"})
    assert [(c.start, c.first, c.end) for c in whole] == [(0, 0, 10)]


def test_inputs_are_found_by_kind_and_named_uniquely(tmp_path: Path) -> None:
    tree = tmp_path / "deploy"
    images(tree / "day1" / "pairs")
    images(tree / "day2" / "kitti", "image_0", "image_1")
    (tree / "day2" / "run.mcap").write_bytes(b"x")
    (tree / "day3" / "bag").mkdir(parents=True)
    (tree / "day3" / "bag" / "metadata.yaml").write_text("rosbag2_bagfile_information: {}\n")
    (tree / "day3" / "sbs.mp4").write_bytes(b"x")
    (tree / "notes.txt").write_text("not an input")
    got = find_inputs([str(tree), str(tree / "day1" / "pairs")])
    assert [(i.name, i.kind) for i in got] == [
        ("deploy__day1__pairs", "images"), ("deploy__day2__kitti", "images"),
        ("deploy__day2__run.mcap", "replay"), ("deploy__day3__bag", "replay"),
        ("deploy__day3__sbs.mp4", "video"), ("pairs", "images")]
    twice = find_inputs([str(tree / "day1" / "pairs")] * 2)
    assert [i.name for i in twice] == ["pairs", "pairs-2"]
    assert find_inputs([f"video:{tmp_path}/l.mp4,{tmp_path}/r.mp4"]) == [
        Input("l.mp4", "video", f"{tmp_path}/l.mp4,{tmp_path}/r.mp4")]


@pytest.mark.parametrize(("make", "error"), [
    (lambda d: str(d / "missing"), "not found or not a known input"),
    (lambda d: (d / "empty").mkdir() or str(d / "empty"), "a folder with no input in it"),
    (lambda d: (d / "a.txt").write_text("x") and str(d / "a.txt"), "not a known input"),
    (lambda d: "v4l2:/dev/video0,/dev/video2", "a v4l2 source never ends"),
    (lambda d: "synthetic:", "a synthetic source never ends"),
    (lambda d: "webcam:0", "unknown kind 'webcam'"),
])
def test_bad_inputs_are_refused_with_the_reason(tmp_path: Path, make: Callable[[Path], str],
                                                error: str) -> None:
    with pytest.raises(ConfigError, match=error):
        find_inputs([make(tmp_path)])


def pose_rows(world: np.ndarray) -> list[list[float]]:
    return [[round(float(v), 6) for v in row] for row in world[:3, :4]]


def step(i: int) -> np.ndarray:
    m = np.eye(4)
    m[0, 3] = 0.1 * i  # 10 cm along x per pair
    return m


def vo_lines(chunk: Chunk, err_at: int | None = None, err: float = 0.0) -> list[dict[str, Any]]:
    """A chunk's VO lines, its poses in its own frame (identity at chunk.start)."""
    out = []
    for s in range(chunk.start, chunk.end):
        rel = np.linalg.inv(step(chunk.start)) @ step(s)
        if err_at is not None and s >= err_at:
            rel[1, 3] += err
        out.append({"stereo_vo": {"seq": s, "ok": True, "pose": pose_rows(rel),
                                  **({"reinit": True} if s == chunk.start else {})}})
    return out


def test_stitched_poses_continue_the_trajectory_and_measure_the_drift() -> None:
    st = Stitcher(decimals=6)
    a, b = Chunk("x", ("vo",), 0, 4, 0), Chunk("x", ("vo",), 2, 8, 4)
    first = st.add(a, vo_lines(a))
    # The second chunk re-initialised at 2 and is 5 cm off in y from pair 3 on.
    second = st.add(b, vo_lines(b, err_at=3, err=0.05))
    assert [x["stereo_vo"]["seq"] for x in first + second] == list(range(8))
    assert [x["stereo_vo"]["pose"][0][3] for x in second] == pytest.approx([0.4, 0.5, 0.6, 0.7])
    assert [x["stereo_vo"]["pose"][1][3] for x in second] == pytest.approx([0.05] * 4)
    (boundary,) = st.boundaries
    assert boundary.as_dict() == {"at": 4, "overlap": 2, "compared_seq": 3,
                                  "drift_translation_m": pytest.approx(0.05),
                                  "drift_rotation_deg": pytest.approx(0.0)}


def test_a_boundary_without_overlap_has_nothing_to_compare() -> None:
    st = Stitcher(decimals=6)
    a, b = Chunk("x", ("vo",), 0, 4, 0), Chunk("x", ("vo",), 4, 8, 4)
    st.add(a, vo_lines(a))
    st.add(b, vo_lines(b))
    assert st.boundaries[0].as_dict()["compared_seq"] is None


@pytest.mark.parametrize(("args", "error"), [
    (["--vo-chunk", "0"], "expected a number of pairs >= 1 or 'whole', got '0'"),
    (["--vo-chunk", "lots"], "expected a number of pairs >= 1 or 'whole'"),
    (["--workers", "mono,,vo"], "expected distinct pool names separated by commas"),
    (["--workers", "mono,mono"], "expected distinct pool names"),
    (["--local", "2", "--scheduler", "tcp://127.0.0.1:1"], "not both"),
    (["--chunk", "0"], "0 is not in the range x>=1"),
])
def test_the_command_line_rejects_bad_options(tmp_path: Path, args: list[str],
                                              error: str) -> None:
    scene = images(tmp_path / "s")
    out = CliRunner().invoke(main, ["process", str(scene), "--out", str(tmp_path / "o"), *args])
    assert out.exit_code == 2, out.output
    assert error in out.output


def test_an_unknown_input_is_a_usage_error(tmp_path: Path) -> None:
    out = CliRunner().invoke(main, ["process", str(tmp_path / "nope")])
    assert out.exit_code == 2
    assert "trapflow: error: input" in out.output and "not found" in out.output


class Stateful(Worker):
    """A plugin that keeps state from pair to pair: each result says how many pairs this
    instance saw before and the seq it saw last (a stand-in for visual odometry)."""

    needs_images = False

    def configure(self, params: Mapping[str, Any], ctx: Context) -> None:
        self.seen: list[int] = []

    def process(self, pair: Pair) -> Extra:
        before = self.seen[-1] if self.seen else -1
        self.seen.append(pair.header.seq)
        return Extra(name="stateful", fields={"before": before, "n": len(self.seen)})


def ordered_config(policy: str) -> Config:
    """A pool named `odometry` (not vo) running Stateful under `policy`, and a `vo` pool
    under `latest`: the name of a pool says nothing, its policy everything."""
    return configmod.from_data({
        "source": {"width": 32, "height": 24},
        "pools": {"odometry": {"count": 1, "plugin": f"{__name__}:Stateful", "policy": policy},
                  "vo": {"count": 1, "plugin": "example_brightness", "policy": "latest"},
                  "mono": {"count": 0}, "stereo": {"count": 0}, "tags": {"count": 0}}},
        "config")


def test_a_pool_is_ordered_by_its_policy_not_its_name(tmp_path: Path) -> None:
    """Regression: `process` took a pool as ordered by its name (vo), the live pipeline by its
    policy; a stateful plugin in a pool of another name got stateless chunks (its state
    reset every 64 pairs, its pairs out of order across workers) and a `vo` pool under
    `latest` a VO grid. Now both decide by PoolConfig.ordered."""
    cfg = ordered_config("ordered:4")
    pools = ("odometry", "vo")
    ordered = ordered_pools(cfg, pools)
    assert ordered == {"odometry"}
    assert ordered_pools(ordered_config("fifo:4"), pools) == frozenset()
    chunks = plan_chunks("a", 6, pools, 2, 3, 1, ordered)
    assert [(c.pools, c.start, c.first, c.end, c.ordered) for c in chunks] == [
        (("vo",), 0, 0, 2, False), (("vo",), 2, 2, 4, False), (("vo",), 4, 4, 6, False),
        (("odometry",), 0, 0, 3, True), (("odometry",), 2, 3, 6, True)]
    # Run the ordered chunks: each starts a fresh plugin (never one kept from a chunk
    # before) that sees its pairs in order from the chunk's start, the overlap included.
    scene = tmp_path / "scene"
    for side in ("left", "right"):
        (scene / side).mkdir(parents=True)
        for i in range(6):
            cv2.imwrite(str(scene / side / f"{i:06d}.png"), np.full((24, 32, 3), 10 * i, np.uint8))
    inp = Input("scene", "images", str(scene))
    data = msgspec.to_builtins(cfg)
    got = []
    for c in (c for c in chunks if c.ordered):
        run_chunk(ChunkTask(data, inp, c, str(tmp_path / "out"), "key"))
        lines, _ledger = chunk_paths(str(tmp_path / "out"), c)
        got.append([json.loads(x)["stateful"] for x in lines.read_bytes().splitlines()])
    assert [[(x["seq"], x["before"], x["n"]) for x in lines] for lines in got] == [
        [(0, -1, 1), (1, 0, 2), (2, 1, 3)],
        [(2, -1, 1), (3, 2, 2), (4, 3, 3), (5, 4, 4)]]
