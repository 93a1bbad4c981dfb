"""Benchmark of `trapflow process`: pairs/s on a LocalCluster of 1 and 2 workers against
the same plugins in one plain in-process loop over the same image folder, the speedup,
and the overhead per pair and per task that Dask adds.

The cluster is started before the clock starts (its start-up is reported on its own).
The same cluster runs the input twice: cold, then warm (models kept by the workers).
Writes process.json and process.md into --out.

Usage: python -m benchmarks.process [--quick] [--repeats 1] [--pairs 96] [--size 320x240]
       [--chunk 8] [--pools mono,stereo,tags] [--out bench-results]
(--repeats N: the plain loop and both clusters N times in turn, each time reported and the
medians; --repeat, its earlier name, still works.)
"""

from __future__ import annotations

import argparse
import io
import os
import resource
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

import cv2
import msgspec

from benchmarks import harness as h
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
    """CPU seconds this Dask worker process has used (all its threads), run by client.run.
    It runs inside the worker, sent by value: it reads its own process with the standard
    library and imports nothing of the benchmarks."""
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
    ap = h.options(__doc__, repeats=1, quick_help="32 pairs")
    ap.add_argument("--pairs", type=int, default=96)
    ap.add_argument("--size", default="320x240")
    ap.add_argument("--chunk", type=int, default=8)
    ap.add_argument("--pools", default="mono,stereo,tags")
    args = ap.parse_args()  # --repeats: a shared machine's speed drifts 5 % a minute
    if args.quick:
        args.pairs = 32
    w, ht = (int(v) for v in args.size.split("x"))
    pools = tuple(args.pools.split(","))
    cfg = Config()
    opts = Options(pools=pools, chunk=args.chunk)
    load0 = os.getloadavg()[0]
    with tempfile.TemporaryDirectory(prefix="trapflow-bench-") as tmp:
        root = Path(tmp)
        write_folder(root / "scene", args.pairs, w, ht)
        inp = find_inputs([str(root / "scene")])[0]
        plain_loop(cfg, inp, min(4, args.pairs), pools, root / "warm")  # models, caches
        default_s, default_cpu = plain_loop(cfg, inp, args.pairs, pools, root / "plain-default")
        worker_setup()  # what every Dask worker does: OpenCV on one thread
        reports = []
        for i in range(args.repeats):
            loop_s, loop_cpu = plain_loop(cfg, inp, args.pairs, pools, root / f"plain{i}")
            runs = [on_cluster(cfg, inp, n, opts, root / f"dask{n}-{i}") for n in (1, 2)]
            reports.append(summarise(args, pools, (loop_s, loop_cpu),
                                     (default_s, default_cpu), runs,
                                     (load0, os.getloadavg()[0])))
    report = reports[0] if len(reports) == 1 else with_medians(reports)
    tables = results(report)
    h.write(args.out, "process", tables)
    print(h.markdown(tables))


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


def results(r: dict[str, Any]) -> list[h.Result]:
    """The runs' table, and with repetitions their speed-ups and the medians."""
    n, dash = r["pairs"], h.Figure("-")
    t = h.Result("process", f"trapflow process ({n} pairs {r['size']}, pools "
                 f"{','.join(r['pools'])}, chunks of {r['chunk']} = {r['tasks']} tasks; load "
                 f"{r['load_before_after'][0]} before, {r['load_before_after'][1]} after)",
                 key="run", data=r, notes=[
        "Warm runs (models already loaded by the workers); the cold run of the same cluster "
        "and its start-up are given apart. Every row runs OpenCV on one thread (what each "
        "Dask worker does) but the first, which shows OpenCV's own threads. CPU ms per pair: "
        "the workers' (all their threads) and this process's (client and scheduler); 'work' "
        "is the workers' less what they burn idle (measured for 3 s before, per second) over "
        "the run's wall time."])

    def row(label: str, s: float, rate: float, speedup: h.Figure, of_ideal: h.Figure,
            vs_one: h.Figure, workers: str, rest: tuple[str, str, str, str]) -> None:
        t.add(label, **{"s": h.Figure(s), "pairs/s": h.Figure(rate), "speed-up vs plain loop":
                        speedup, "of workers x loop": of_ideal, "vs 1 worker": vs_one,
                        "CPU ms/pair workers (work)": h.Figure(workers),
                        "CPU ms/pair client": h.Figure(rest[0]),
                        "idle CPU ms/s workers, client": h.Figure(rest[1]),
                        "cold run s": h.Figure(rest[2]), "cluster start s": h.Figure(rest[3])})

    row("plain loop, OpenCV default threads", r["plain_default_threads_s"],
        round(n / r["plain_default_threads_s"], 2), dash, dash, dash,
        str(r["plain_default_threads_cpu_ms_per_pair"]), ("-", "-", "-", "-"))
    row("plain loop, 1 process", r["plain_loop_s"], r["plain_pairs_per_s"], h.Figure(1.0),
        dash, dash, str(r["plain_cpu_ms_per_pair"]), ("-", "-", "-", "-"))
    for d in r["dask"]:
        row(f"LocalCluster, {d['workers']} worker(s)", d["seconds"], d["pairs_per_s"],
            h.Figure(d["speedup"]), h.Figure(d["of_ideal"]), h.Figure(d["vs_one_worker"]),
            f"{d['worker_cpu_ms_per_pair']} ({d['worker_work_ms_per_pair']})",
            (str(d["client_cpu_ms_per_pair"]),
             f"{d['idle_worker_cpu_ms_per_s']}, {d['idle_client_cpu_ms_per_s']}",
             str(d["cold_s"]), str(d["cluster_start_s"])))
    if "repeats" not in r:
        return [t]
    reps = h.Result("process", key="repetition", notes=[
        f"{len(r['repeats'])} repetitions in turn (the table above is the last)."])
    for i, rep in enumerate(r["repeats"]):
        reps.add(str(i + 1), **{k: h.Figure(v) for k, v in rep.items()})
    reps.add("**median**", **{k: h.Figure(v) for k, v in r["medians"].items()})
    return [t, reps]


if __name__ == "__main__":
    main()
