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
import os
import resource
import statistics
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
from trapflow.batch.run import Options, dask_client, process, worker_setup
from trapflow.calibration.camera import StereoRig
from trapflow.config.schema import Config

IDLE_S = 3.0  # seconds the idle cluster is measured


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


def plain_loop(cfg: Config, inp: Input, n: int, pools: tuple[str, ...], out: Path
               ) -> tuple[float, float]:
    """(seconds, CPU seconds) for the same plugins over every pair in this process, one
    chunk, no Dask."""
    task = ChunkTask(msgspec.to_builtins(cfg), inp, Chunk(inp.name, pools, 0, n, 0),
                     str(out), "plain")
    c0, t0 = time.process_time(), time.perf_counter()
    run_chunk(task)
    return time.perf_counter() - t0, time.process_time() - c0


def worker_cpu() -> float:
    """CPU seconds this Dask worker process has used (all its threads), run by client.run."""
    use = resource.getrusage(resource.RUSAGE_SELF)
    return use.ru_utime + use.ru_stime


def on_cluster(cfg: Config, inp: Input, workers: int, opts: Options, out: Path) -> dict[str, Any]:
    """Seconds of `process` on an already started LocalCluster of `workers` workers: cold
    (each worker loads its models in its first task) and then warm (the same cluster again,
    models kept by the workers: what every later input of a long run costs), with the CPU
    seconds of the warm run in the workers and in this process (client and scheduler)."""
    t0 = time.perf_counter()
    with dask_client(Options(pools=opts.pools, local=workers)) as client:
        started = time.perf_counter() - t0
        run = Options(pools=opts.pools, chunk=opts.chunk, retries=0,
                      scheduler=client.scheduler.address)
        times, cpu = [], 0.0
        # What the workers and this process burn with nothing to do (heartbeats, the
        # profiler, event loops): a cost per second, not per pair, that a loaded machine
        # (slow pairs) spreads over fewer pairs.
        b, c1 = sum(client.run(worker_cpu).values()), time.process_time()
        time.sleep(IDLE_S)
        idle = ((sum(client.run(worker_cpu).values()) - b) / IDLE_S,
                (time.process_time() - c1) / IDLE_S)
        for name in ("cold", "warm"):
            before = sum(client.run(worker_cpu).values())
            c1, t1 = time.process_time(), time.perf_counter()
            process(cfg, [inp], out / name, run, echo=lambda s: None,
                    progress_stream=io.StringIO())
            times.append(time.perf_counter() - t1)
            cpu = sum(client.run(worker_cpu).values()) - before
            client_cpu = time.process_time() - c1
    return {"workers": workers, "cluster_start_s": round(started, 2), "cold_s": times[0],
            "seconds": times[1], "worker_cpu_s": cpu, "client_cpu_s": client_cpu,
            "idle_worker_cpu_ms_per_s": round(1000 * idle[0], 1),
            "idle_client_cpu_ms_per_s": round(1000 * idle[1], 1)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--out", type=Path, default=Path("bench-results"))
    ap.add_argument("--pairs", type=int, default=96)
    ap.add_argument("--size", default="320x240")
    ap.add_argument("--chunk", type=int, default=8)
    ap.add_argument("--pools", default="mono,stereo,tags")
    ap.add_argument("--repeat", type=int, default=1,
                    help="measure the plain loop and both clusters this many times in turn "
                         "and report each time and the medians (a shared machine's speed "
                         "drifts by 5 %% from one minute to the next)")
    args = ap.parse_args()
    w, h = (int(v) for v in args.size.split("x"))
    pools = tuple(args.pools.split(","))
    cfg = Config()
    opts = Options(pools=pools, chunk=args.chunk)
    load0 = os.getloadavg()[0]
    with tempfile.TemporaryDirectory(prefix="trapflow-bench-") as tmp:
        root = Path(tmp)
        write_folder(root / "scene", args.pairs, w, h)
        inp = find_inputs([str(root / "scene")])[0]
        plain_loop(cfg, inp, min(4, args.pairs), pools, root / "warm")  # models, caches
        default_s, default_cpu = plain_loop(cfg, inp, args.pairs, pools, root / "plain-default")
        worker_setup()  # what every Dask worker does: OpenCV on one thread
        reports = []
        for i in range(args.repeat):
            loop_s, loop_cpu = plain_loop(cfg, inp, args.pairs, pools, root / f"plain{i}")
            runs = [on_cluster(cfg, inp, n, opts, root / f"dask{n}-{i}") for n in (1, 2)]
            reports.append(summarise(args, pools, (loop_s, loop_cpu),
                                     (default_s, default_cpu), runs,
                                     (load0, os.getloadavg()[0])))
    report = reports[0] if len(reports) == 1 else with_medians(reports)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "process.json").write_text(json.dumps(report, indent=2))
    md = markdown(report)
    (args.out / "process.md").write_text(md)
    print(md)


def summarise(args: argparse.Namespace, pools: tuple[str, ...], loop: tuple[float, float],
              default: tuple[float, float], runs: list[dict[str, Any]],
              load: tuple[float, float]) -> dict[str, Any]:
    """Rates, speed-ups against the one-thread plain loop and against one Dask worker (the
    same run), CPU ms per pair."""
    n = args.pairs
    tasks = -(-n // args.chunk)
    loop_s, loop_cpu = loop
    loop_rate = n / loop_s
    one = n / runs[0]["seconds"]
    rows = []
    for r in runs:
        rate = n / r["seconds"]
        overhead = (r["seconds"] * r["workers"] - loop_s) / n
        rows.append({**r, "seconds": round(r["seconds"], 2), "cold_s": round(r["cold_s"], 2),
                     "pairs_per_s": round(rate, 2),
                     "speedup": round(rate / loop_rate, 2),
                     "of_ideal": round(rate / (loop_rate * r["workers"]), 2),
                     "vs_one_worker": round(rate / one, 2),
                     "worker_cpu_ms_per_pair": round(1000 * r["worker_cpu_s"] / n, 1),
                     # the same less the idle cost over the run's wall time: the work per pair
                     "worker_work_ms_per_pair": round(
                         (1000 * r["worker_cpu_s"] - r["idle_worker_cpu_ms_per_s"]
                          * r["seconds"]) / n, 1),
                     "client_cpu_ms_per_pair": round(1000 * r["client_cpu_s"] / n, 1),
                     "overhead_ms_per_pair": round(1000 * overhead, 1),
                     "overhead_ms_per_task": round(1000 * overhead * n / tasks, 1)})
    return {"pairs": n, "size": args.size, "pools": list(pools), "chunk": args.chunk,
            "tasks": tasks, "plain_loop_s": round(loop_s, 2),
            "plain_pairs_per_s": round(loop_rate, 2),
            "plain_cpu_ms_per_pair": round(1000 * loop_cpu / n, 1),
            "plain_default_threads_s": round(default[0], 2),
            "plain_default_threads_cpu_ms_per_pair": round(1000 * default[1] / n, 1),
            "load_before_after": [round(x, 2) for x in load], "dask": rows}


def with_medians(reports: list[dict[str, Any]]) -> dict[str, Any]:
    """The last repetition's report, with every repetition's speed-ups and their medians."""
    def median(xs: list[float]) -> float:
        return round(statistics.median(xs), 2)

    out = dict(reports[-1])
    out["repeats"] = [{"plain_cpu_ms_per_pair": r["plain_cpu_ms_per_pair"],
                       **{f"{d['workers']}w_{k}": d[k] for d in r["dask"]
                          for k in ("speedup", "vs_one_worker", "worker_work_ms_per_pair")}}
                      for r in reports]
    out["medians"] = {k: median([rep[k] for rep in out["repeats"]])
                      for k in out["repeats"][0]}
    return out


def markdown(r: dict[str, Any]) -> str:
    n = r["pairs"]
    lines = [f"## trapflow process ({n} pairs {r['size']}, pools {','.join(r['pools'])}, "
             f"chunks of {r['chunk']} = {r['tasks']} tasks; load {r['load_before_after'][0]}"
             f" before, {r['load_before_after'][1]} after)", "",
             "Warm runs (models already loaded by the workers); the cold run of the same "
             "cluster and its start-up are given apart. Every row runs OpenCV on one thread "
             "(what each Dask worker does) but the first, which shows OpenCV's own threads. "
             "CPU ms per pair: the workers' (all their threads) and this process's (client "
             "and scheduler); 'work' is the workers' less what they burn idle (measured "
             "for 3 s before, per second) over the run's wall time.", "",
             "| run | s | pairs/s | speed-up vs plain loop | of workers x loop | vs 1 worker "
             "| CPU ms/pair workers (work) | CPU ms/pair client | idle CPU ms/s workers, "
             "client | cold run s | cluster start s |",
             "|---|---|---|---|---|---|---|---|---|---|---|",
             f"| plain loop, OpenCV default threads | {r['plain_default_threads_s']:.2f} | "
             f"{n / r['plain_default_threads_s']:.2f} | - | - | - | "
             f"{r['plain_default_threads_cpu_ms_per_pair']} | - | - | - | - |",
             f"| plain loop, 1 process | {r['plain_loop_s']:.2f} | {r['plain_pairs_per_s']:.2f} "
             f"| 1.00 | - | - | {r['plain_cpu_ms_per_pair']} | - | - | - | - |"]
    lines += [f"| LocalCluster, {d['workers']} worker(s) | {d['seconds']} | {d['pairs_per_s']} "
              f"| {d['speedup']} | {d['of_ideal']} | {d['vs_one_worker']} "
              f"| {d['worker_cpu_ms_per_pair']} ({d['worker_work_ms_per_pair']}) "
              f"| {d['client_cpu_ms_per_pair']} | {d['idle_worker_cpu_ms_per_s']}, "
              f"{d['idle_client_cpu_ms_per_s']} | {d['cold_s']} | {d['cluster_start_s']} |"
              for d in r["dask"]]
    if "repeats" in r:
        keys = list(r["medians"])
        lines += ["", f"{len(r['repeats'])} repetitions in turn (the table above is the last):",
                  "", "| repetition | " + " | ".join(keys) + " |",
                  "|---" * (len(keys) + 1) + "|"]
        lines += [f"| {i + 1} | " + " | ".join(str(rep[k]) for k in keys) + " |"
                  for i, rep in enumerate(r["repeats"])]
        lines.append("| **median** | " + " | ".join(f"**{r['medians'][k]}**" for k in keys)
                     + " |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
