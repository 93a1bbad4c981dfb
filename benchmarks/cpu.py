"""Benchmark: CPU per captured pair by process role, and the VO floor under saturating recognisers.

Part `cpu`: the default pipeline (synthetic 1280x720, mono + stereo + vo) at fixed capture
rates, once as configured, once with `--encoding raw` and once with `--encoding jpeg`. For
every process role: CPU seconds (user + system, psutil) per captured pair over a window,
and for workers the part spent inside the plugin's process() (the workers' proc_us).
Part `floor`: a plugin that burns CPU (not sleeps) 2 s per pair in the stereo pool and
100 ms in two mono workers, beside the real VO: VO pairs/s against the capture rate.

Usage: python -m benchmarks.cpu [--quick] [--parts cpu,floor] [--out bench-results]
Writes cpu.json and cpu.md into the output folder.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import psutil
import yaml

from benchmarks import harness as h

ROLES = ("capture", "worker:mono", "worker:stereo", "worker:vo")
OTHER = "broker + normalizer + supervisor"


def _status(run: Path) -> dict[str, Any] | None:
    out = subprocess.run([sys.executable, "-m", "trapflow", "status", "--json", "--run-dir",
                          str(run), "--timeout", "2"], capture_output=True, text=True, timeout=20)
    if out.returncode != 0:
        return None
    try:
        s: dict[str, Any] = json.loads(out.stdout)
    except ValueError:
        return None
    return s


def _snapshot(sup: int, run: Path) -> tuple[dict[int, tuple[str, float, int]], int,
                                             dict[str, Any]]:
    """Per process: (role, CPU seconds, CPU microseconds inside process()); pairs captured;
    the broker's counters per pool."""
    s = _status(run)
    if s is None:
        raise SystemExit("status did not answer during the window")
    # a row per process: each its own CPU (the supervisor's children have rows of their own)
    procs: dict[int, tuple[str, float, int]] = {sup: (OTHER, h.tree_cpu(sup, children=False),
                                                      0)}
    produced = 0
    for n in s["nodes"]:
        if not n["pid"]:
            continue
        role = n["name"].rsplit(":", 1)[0] if n["name"].startswith("worker:") else n["name"]
        c = n.get("counters") or {}
        procs[n["pid"]] = (role if role in ROLES else OTHER,
                           h.tree_cpu(n["pid"], children=False),
                           int(c.get("proc_cpu_us", 0)))
        if n["name"] == "capture":
            produced = int(c.get("produced", 0))
    pools = (s.get("stats") or {}).get("pools") or {}
    return procs, produced, pools


def run_window(args: list[str], warmup: float, window: float,
               config: dict[str, Any] | None = None) -> dict[str, Any]:
    """One `trapflow start` with args; measured from warmup for window seconds."""
    tmp = Path(tempfile.mkdtemp(prefix="tf-bench-cpu-"))
    run = tmp / "run"
    extra: list[str] = []
    if config is not None:
        (tmp / "c.yaml").write_text(yaml.safe_dump(config))
        extra = ["--config", str(tmp / "c.yaml")]
    p = subprocess.Popen([sys.executable, "-m", "trapflow", "start", "--run-dir", str(run),
                          *extra, *args], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                         start_new_session=True)
    try:
        deadline = time.monotonic() + 120
        while True:
            s = _status(run) if run.exists() else None
            if s and s.get("stats") and all(n["state"] == "active" for n in s["nodes"]):
                break
            if time.monotonic() > deadline or p.poll() is not None:
                raise SystemExit(f"trapflow start {' '.join(args)} did not become active")
            time.sleep(0.5)
        time.sleep(warmup)
        s0, n0, v0 = _snapshot(p.pid, run)
        t0 = time.monotonic()
        time.sleep(window)
        s1, n1, v1 = _snapshot(p.pid, run)
        dt = time.monotonic() - t0
    finally:
        p.send_signal(signal.SIGINT)
        try:
            p.wait(30)
        except subprocess.TimeoutExpired:
            p.kill()
    pairs = max(n1 - n0, 1)
    cpu = dict.fromkeys((*ROLES, OTHER), 0.0)
    inside = dict.fromkeys((*ROLES, OTHER), 0.0)
    restarted = 0
    for pid, (role, c, us) in s1.items():
        if pid not in s0:  # started inside the window (a restart): not comparable
            restarted += 1
            continue
        cpu[role] += c - s0[pid][1]
        inside[role] += (us - s0[pid][2]) / 1e6
    done = {f"worker:{k}": v1[k].get("processed", 0) - v0.get(k, {}).get("processed", 0)
            for k in v1}
    # Per processed pair for workers (a pool that drops pairs on a loaded machine would look
    # cheaper per captured pair); per captured pair for the rest.
    roles = {r: {"cpu_ms": round(1000 * cpu[r] / pairs, 2),
                 "process_ms": round(1000 * inside[r] / pairs, 2),
                 "processed": done.get(r, pairs),
                 "cpu_ms_per_processed": round(1000 * cpu[r] / max(done.get(r, pairs), 1), 2),
                 "process_ms_per_processed": round(1000 * inside[r] / max(done.get(r, pairs), 1),
                                                   2)} for r in cpu}
    total = round(sum(v["cpu_ms"] for v in roles.values()), 2)
    every = round(sum(v["cpu_ms_per_processed"] for v in roles.values()), 2)
    vo = {k: v1.get("vo", {}).get(k, 0) - v0.get("vo", {}).get(k, 0)
          for k in ("received", "processed", "dropped")}
    return {"args": args, "window_s": round(dt, 1), "pairs": pairs,
            "capture_hz": round(pairs / dt, 2), "vo_hz": round(vo["processed"] / dt, 2),
            "vo": vo, "restarted_in_window": restarted, "roles": roles, "total_cpu_ms": total,
            "every_pool_cpu_ms": every}


def part_cpu(rates: list[float], warmup: float, window: float) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for rate in rates:
        for name, enc in (("default", []), ("raw", ["--encoding", "raw"]),
                          ("jpeg", ["--encoding", "jpeg"])):
            h.log("cpu", f"{name} at {rate:g} pairs/s")
            out[f"{name}@{rate:g}"] = run_window(["--rate", str(rate), *enc], warmup, window)
    return out


def part_floor(rate: float, warmup: float, window: float,
               extra: tuple[str, ...] | list[str] = ()) -> dict[str, Any]:
    burn = "trapflow.testing.plugins:Burn"
    cfg = {"pools": {"stereo": {"plugin": burn, "params": {"cpu_s": 2.0}, "timeout_s": 120.0},
                     "mono": {"plugin": burn, "count": 2, "params": {"cpu_s": 0.1}}}}
    h.log("cpu", f"VO floor at {rate:g} pairs/s")
    return run_window(["--rate", str(rate), *extra], warmup, window, cfg)


def results(r: dict[str, Any]) -> list[h.Result]:
    """A table per rate (roles by run) and the VO floor in words."""
    out = [_rate_table(r, rate) for rate in r["rates"]]
    if "floor" in r:
        f = r["floor"]
        out.append(h.Result("cpu", "VO floor under saturating recognisers", notes=[
            f"stereo burns 2 s CPU per pair, two mono workers 100 ms each: capture "
            f"{f['capture_hz']} pairs/s, VO {f['vo_hz']} pairs/s (window {f['window_s']} s; "
            f"VO pool received {f['vo']['received']}, dropped {f['vo']['dropped']})."]))
    out[0].data = r
    return out


def _rate_table(r: dict[str, Any], rate: float) -> h.Result:
    runs = {k.split("@")[0]: v for k, v in r["cpu"].items() if k.endswith(f"@{rate:g}")}
    t = h.Result("cpu", f"CPU per captured pair by process role ({r['cores']} cores, synthetic "
                 f"1280x720, mono + stereo + vo; load average {r['load']})" if rate ==
                 r["rates"][0] else "", key="role", notes=[
        f"At {rate:g} pairs/s requested (reached: " + ", ".join(
            f"{k} {v['capture_hz']}" for k, v in runs.items()) + "). CPU ms per pair: per "
        "captured pair for capture and the rest, per pair it processed for a worker (its "
        "pairs processed in the window after the slash); in brackets the part inside "
        "process(). The total is what one pair costs when every pool processes it."])
    for role in (*ROLES, OTHER):
        cells = {}
        for name, v in runs.items():
            x = v["roles"][role]
            cells[name] = h.Figure(f"{x['cpu_ms_per_processed']:.1f}" + (
                f" ({x['process_ms_per_processed']:.1f}) / {x['processed']}"
                if role.startswith("worker:") else ""), "ms")
        t.add(role, **cells)
    t.add("**total**", **{name: h.Figure(f"**{v['every_pool_cpu_ms']:.1f}**", "ms")
                          for name, v in runs.items()})
    d, raw = runs["default"]["every_pool_cpu_ms"], runs["raw"]["every_pool_cpu_ms"]
    inside = sum(x["process_ms_per_processed"] for x in runs["default"]["roles"].values())
    source = runs["default"]["roles"]["capture"]["cpu_ms"]
    t.notes.append(f"default / raw: **{d / raw:.2f}x**; jpeg / raw: "
                   f"{runs['jpeg']['every_pool_cpu_ms'] / raw:.2f}x; default outside process() "
                   f"and the source (capture): {100 * (d - inside - source) / d:.0f} % of the "
                   "total.")
    return t


def main() -> None:
    ap = h.options(__doc__, repeats=1, quick_help="short windows (about 3 minutes)")
    ap.add_argument("--parts", default="cpu,floor", help="comma-separated: cpu, floor")
    args = ap.parse_args()
    warmup, window = (6.0, 8.0) if args.quick else (15.0, 30.0)
    parts = set(args.parts.split(","))
    rates = [10.0, 15.0]
    r: dict[str, Any] = {"bench": "cpu_per_pair", "cores": psutil.cpu_count(), "rates": rates,
                         "quick": args.quick}
    if "cpu" in parts:
        r["cpu"] = part_cpu(rates, warmup, window)
    if "floor" in parts:
        r["floor"] = part_floor(15.0, warmup, window)
    r["load"] = " ".join(f"{x:.1f}" for x in psutil.getloadavg())
    if "cpu" not in r:
        r["cpu"], r["rates"] = {}, []
    tables = results(r) if r["rates"] or "floor" in r else [h.Result("cpu", data=r)]
    h.write(args.out, "cpu", tables)
    print(h.markdown(tables))


if __name__ == "__main__":
    main()
