"""Benchmark of `trapflow process`: pairs/s on a LocalCluster of 1 and 2 workers against
the same plugins in one plain in-process loop over the same image folder, the speedup,
and the overhead per pair and per task that Dask adds.

The cluster is started before the clock starts (its start-up is reported on its own).
The same cluster runs the input twice: cold, then warm (models kept by the workers).
Writes process.json and process.md into --out.
"""

from __future__ import annotations

import argparse
import io
import json
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import cv2
import msgspec

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repository: tests.kits
from tests.kits.scenes import FloorWorld, looking_down
from trapflow.batch.chunk import ChunkTask, run_chunk
from trapflow.batch.plan import Chunk, Input, find_inputs
from trapflow.batch.run import Options, dask_client, process
from trapflow.calibration.camera import StereoRig
from trapflow.config.schema import Config


def write_folder(root: Path, n: int, width: int, height: int) -> None:
    """n pairs of a textured floor seen by a rig moving 2 cm per pair."""
    rig = StereoRig.from_fov(width, height, 70.0, 0.12)
    world = FloorWorld.square(rig, 4.0, res_m=0.003, seed=5)
    for side in ("left", "right"):
        (root / side).mkdir(parents=True)
    for i in range(n):
        left, right = world.render(looking_down(-0.01 * n + 0.02 * i, 0.0, 1.2, 0.0, pitch=0.0))
        cv2.imwrite(str(root / "left" / f"{i:06d}.png"), left)
        cv2.imwrite(str(root / "right" / f"{i:06d}.png"), right)


def plain_loop(cfg: Config, inp: Input, n: int, pools: tuple[str, ...], out: Path) -> float:
    """Seconds for the same plugins over every pair in this process, one chunk, no Dask."""
    task = ChunkTask(msgspec.to_builtins(cfg), inp, Chunk(inp.name, pools, 0, n, 0),
                     str(out), "plain")
    t0 = time.perf_counter()
    run_chunk(task)
    return time.perf_counter() - t0


def on_cluster(cfg: Config, inp: Input, workers: int, opts: Options, out: Path) -> dict[str, Any]:
    """Seconds of `process` on an already started LocalCluster of `workers` workers: cold
    (each worker loads its models in its first task) and then warm (the same cluster again,
    models kept by the workers: what every later input of a long run costs)."""
    t0 = time.perf_counter()
    with dask_client(Options(pools=opts.pools, local=workers)) as client:
        started = time.perf_counter() - t0
        run = Options(pools=opts.pools, chunk=opts.chunk, retries=0,
                      scheduler=client.scheduler.address)
        times = []
        for name in ("cold", "warm"):
            t1 = time.perf_counter()
            process(cfg, [inp], out / name, run, echo=lambda s: None,
                    progress_stream=io.StringIO())
            times.append(time.perf_counter() - t1)
    return {"workers": workers, "cluster_start_s": round(started, 2), "cold_s": times[0],
            "seconds": times[1]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--out", type=Path, default=Path("bench-results"))
    ap.add_argument("--pairs", type=int, default=48)
    ap.add_argument("--size", default="320x240")
    ap.add_argument("--chunk", type=int, default=8)
    ap.add_argument("--pools", default="mono,stereo,tags")
    args = ap.parse_args()
    w, h = (int(v) for v in args.size.split("x"))
    pools = tuple(args.pools.split(","))
    cfg = Config()
    opts = Options(pools=pools, chunk=args.chunk)
    with tempfile.TemporaryDirectory(prefix="trapflow-bench-") as tmp:
        root = Path(tmp)
        write_folder(root / "scene", args.pairs, w, h)
        inp = find_inputs([str(root / "scene")])[0]
        plain_loop(cfg, inp, min(4, args.pairs), pools, root / "warm")  # models, caches
        loop_s = plain_loop(cfg, inp, args.pairs, pools, root / "plain")
        runs = [on_cluster(cfg, inp, n, opts, root / f"dask{n}") for n in (1, 2)]
    n = args.pairs
    tasks = -(-n // args.chunk)
    loop_rate = n / loop_s
    rows = []
    for r in runs:
        rate = n / r["seconds"]
        overhead = (r["seconds"] * r["workers"] - loop_s) / n
        rows.append({**r, "seconds": round(r["seconds"], 2), "cold_s": round(r["cold_s"], 2),
                     "pairs_per_s": round(rate, 2),
                     "speedup": round(rate / loop_rate, 2),
                     "of_ideal": round(rate / (loop_rate * r["workers"]), 2),
                     "overhead_ms_per_pair": round(1000 * overhead, 1),
                     "overhead_ms_per_task": round(1000 * overhead * n / tasks, 1)})
    report = {"pairs": n, "size": args.size, "pools": list(pools), "chunk": args.chunk,
              "tasks": tasks, "plain_loop_s": round(loop_s, 2),
              "plain_pairs_per_s": round(loop_rate, 2), "dask": rows}
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "process.json").write_text(json.dumps(report, indent=2))
    lines = [f"## trapflow process ({n} pairs {args.size}, pools {args.pools}, chunks of "
             f"{args.chunk} = {tasks} tasks)", "",
             "Warm runs (models already loaded by the workers); the cold run of the same "
             "cluster and its start-up are given apart.", "",
             "| run | s | pairs/s | speedup | of workers x loop | overhead ms/pair | "
             "overhead ms/task | cold run s | cluster start s |",
             "|---|---|---|---|---|---|---|---|---|",
             f"| plain loop, 1 process | {loop_s:.2f} | {loop_rate:.2f} | 1.00 | - | - | - | - "
             "| - |"]
    lines += [f"| LocalCluster, {r['workers']} worker(s) | {r['seconds']} | {r['pairs_per_s']} "
              f"| {r['speedup']} | {r['of_ideal']} | {r['overhead_ms_per_pair']} | "
              f"{r['overhead_ms_per_task']} | {r['cold_s']} | {r['cluster_start_s']} |"
              for r in rows]
    md = "\n".join(lines) + "\n"
    (args.out / "process.md").write_text(md)
    print(md)


if __name__ == "__main__":
    main()
