"""The transport benchmark's tables (benchmarks/transport.py), from its report: pure, the
ratios against raw pyzmq in the same run; the report carries its window and frame paths."""

from __future__ import annotations

from typing import Any

from benchmarks import harness as h


def results(out: dict[str, Any]) -> list[h.Result]:
    """The transport's tables, ratios against raw pyzmq in the same run."""
    return [_throughput(out), _fanout(out), _latency(out)]


def _throughput(out: dict[str, Any]) -> h.Result:
    m, repeats = out["machine"], out["repeats"]
    r = h.Result("transport", "Transport: trapflow vs raw pyzmq PUSH/PULL (same run, same "
                 "payload)", key="payload, path", data=out, notes=[
        f"{m['cores']} cores, Python {m['python']}, pyzmq {m['pyzmq']}, libzmq {m['libzmq']}. "
        f"1280x720 stereo pairs; lossless, {out['window']} pairs in flight per consumer; consumers "
        "touch every page. trapflow-zmq: bytes through the broker; trapflow-shm: copied once "
        "into the shared-memory ring by the harness (capture), descriptors through the broker "
        "over local links; trapflow-shm_inplace: the same, the pair made in its slot (a byte "
        "a page touched, no copy on either side: the ring's own cost). Throughput: median of "
        f"{repeats} runs (pyzmq and trapflow interleaved), [min-max] next to it; x pyzmq: "
        "ratio of the medians, [min-max] of the ratios run by run (each trapflow run against "
        "the pyzmq run just before it)."])
    for kind in ("jpeg", "raw"):
        t = out[kind]["throughput"]
        b = t["pyzmq_push_pull"]
        r.add(f"{kind}, pyzmq PUSH/PULL", **{
            "pairs/s": _rate(b), "x pyzmq": h.Figure(1.0), "CPU": h.Figure(
                round(b["cpu_us_per_pair"]), "us/pair"), "by process": h.Figure(None, "us/pair")})
        for f in out["frames"]:
            run, paired = t[f"trapflow_{f}"], t[f"paired_{f}"]
            by = ", ".join(f"{k} {v}" for k, v in run["cpu_us_per_pair_by_process"].items())
            r.add(f"{kind}, trapflow-{f}", **{
                "pairs/s": _rate(run),
                "x pyzmq": h.Figure(round(t[f"ratio_{f}"], 3), "",
                                    *((min(paired), max(paired)) if len(paired) > 1 else ())),
                "CPU": h.Figure(round(run["cpu_us_per_pair"]), "us/pair"),
                "by process": h.Figure(by, "us/pair")})
    r.notes.append(f"Load average {out['load']['before']} before, {out['load']['after']} "
                   "after.")
    return r


def _fanout(out: dict[str, Any]) -> h.Result:
    fan = out["raw"]["fanout3"]
    base = fan["pyzmq_push_pull"]["pairs_s"]
    r = h.Result("transport", "Fan-out, raw pairs, 1 source -> 3 pools (every pool gets every "
                 "pair), pairs/s per pool (slowest)", key="path")
    r.add("pyzmq PUSH/PULL x3", **{"pairs/s": h.Figure(round(base, 1), digits=0),
                                   "x pyzmq": h.Figure(1.0)})
    for f in out["frames"]:
        rate = fan[f"trapflow_{f}"]["pairs_s"]
        r.add(f"trapflow-{f}", **{"pairs/s": h.Figure(round(rate, 1), digits=0),
                                  "x pyzmq": h.Figure(round(rate / base, 3))})
    return r


def _latency(out: dict[str, Any]) -> h.Result:
    r = h.Result("transport", "One-way latency at 30 pairs/s", key="payload, path", notes=[
        "Capture stamp before send -> the worker holds the pair. JPEG decode of one "
        f"1280x720 pair costs a worker {out['jpeg_decode']['decode_ms_per_pair']:.1f} ms of "
        "CPU (one core); with raw frames in the ring no worker decodes anything."])
    for kind in ("jpeg", "raw"):
        lat = out[kind]["latency_30hz"]
        b = lat["pyzmq_push_pull"]["lat_us"]
        r.add(f"{kind}, pyzmq", **_pcts_figures(b), **{"x pyzmq p50": h.Figure(1.0)})
        for f in out["frames"]:
            run = lat[f"trapflow_{f}"]
            rss = ", ".join(f"{k} {v:.0f}" for k, v in run["rss_mb"].items())
            r.add(f"{kind}, trapflow-{f}", **_pcts_figures(run["lat_us"]), **{
                "x pyzmq p50": h.Figure(round(lat[f"ratio_p50_{f}"], 3)),
                "broker CPU": h.Figure(round(run["broker_cpu_pct"], 2), "% of a core",
                                       digits=1),
                "peak RSS": h.Figure(rss, "MB")})
    return r


def _pcts_figures(lat_us: dict[str, float]) -> dict[str, h.Figure]:
    return {k: h.Figure(round(lat_us[k], 1), "us", digits=0) for k in ("p50", "p99", "max")}


def _rate(run: dict[str, Any], digits: int = 0) -> h.Figure:
    """Pairs/s of the median run with the [min-max] of all runs."""
    s = h.summarise(run.get("pairs_s_runs") or [run["pairs_s"]])
    return h.Figure(round(run["pairs_s"], 1), "", s.low if s.n > 1 else None,
                    s.high if s.n > 1 else None, digits)
