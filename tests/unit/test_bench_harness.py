"""The benchmarks' harness (benchmarks/harness.py): median and spread against values worked
by hand, the markdown table, the JSON round trip, and the CPU of a process tree measured on
a real child that burns CPU."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from benchmarks import harness as h

REPO = Path(__file__).resolve().parents[2]
BENCHES = REPO / "benchmarks"
# Modules of the package that are not benches: the harness, and parts other benches import.
NOT_BENCHES = {"__init__", "harness", "gate_pipeline", "tracking_realdata", "tune_tracking",
               "transport_report"}


def test_median_and_range_of_an_odd_count() -> None:
    s = h.summarise([5.0, 1.0, 3.0, 9.0, 2.0])
    # sorted 1 2 3 5 9: the middle one, and the ends
    assert (s.median, s.low, s.high, s.n) == (3.0, 1.0, 9.0, 5)


def test_median_of_an_even_count_is_the_mean_of_the_middle_two() -> None:
    s = h.summarise([4.0, 1.0, 10.0, 2.0])
    # sorted 1 2 4 10: (2 + 4) / 2
    assert (s.median, s.low, s.high) == (3.0, 1.0, 10.0)


def test_interquartile_range_by_hand() -> None:
    # sorted 1 2 3 4 5 6 7 8 9: inclusive quartiles at positions 2 and 6 (0-based) of the
    # nine, i.e. 3 and 7; the outliers 1 and 9 do not move them.
    s = h.summarise([9, 1, 8, 2, 7, 3, 6, 4, 5], spread="iqr")
    assert (s.median, s.low, s.high) == (5.0, 3.0, 7.0)
    # sorted 1 2 3 4: inclusive quartiles at positions 0.75 and 2.25: 1.75 and 3.25
    s4 = h.summarise([4, 3, 2, 1], spread="iqr")
    assert (s4.median, s4.low, s4.high) == (2.5, 1.75, 3.25)


def test_one_sample_is_its_own_spread_and_none_is_refused() -> None:
    assert h.summarise([2.5], spread="iqr") == h.Summary(2.5, 2.5, 2.5, 1, "iqr")
    with pytest.raises(ValueError):
        h.summarise([])


def test_repeat_and_per_call() -> None:
    values = iter([3.0, 1.0, 2.0])
    assert h.repeat(lambda: next(values), 3) == [3.0, 1.0, 2.0]
    ticks = iter(range(100))
    calls = []
    # a fake clock: 1 tick read before and one after 4 calls, the warm-up call not timed
    per = h.per_call(lambda: calls.append(1), 4, clock=lambda: float(next(ticks)) * 8)
    assert len(calls) == 5 and per == 2.0


def test_figure_scales_a_summary() -> None:
    f = h.figure(h.summarise([0.001, 0.002, 0.004]), "ms", scale=1000, digits=1)
    assert (f.value, f.low, f.high, f.unit) == (2.0, 1.0, 4.0, "ms")
    assert h.cell(f) == "2.0 [1.0-4.0]"
    assert h.cell(h.figure(h.summarise([0.5]), "s")) == "0.50"  # one run: no spread


def _result() -> h.Result:
    r = h.Result("decode", "JPEG decode", key="operation", notes=["One thread."],
                 data={"decoder": "simplejpeg", "sizes": [[1280, 720]]})
    r.add("cv2 colour", time=h.Figure(5.25, "ms", 5.0, 6.0), kind=h.Figure("colour"))
    r.add("cv2 grey", time=h.Figure(1234.5, "ms", digits=1))
    return r


def test_markdown_table() -> None:
    text = h.markdown([_result()])
    assert text == (
        "## JPEG decode\n\n"
        "| operation | time (ms) | kind |\n"
        "|---|---:|---|\n"
        "| cv2 colour | 5.25 [5.00-6.00] | colour |\n"
        "| cv2 grey | 1,234.5 |  |\n\n"
        "One thread.\n")


def test_columns_keep_the_order_first_seen_and_ints_print_whole() -> None:
    rows = [h.Row("a", {"n": h.Figure(3)}), h.Row("b", {"x": h.Figure(1.5, "s"),
                                                      "n": h.Figure(10_000)})]
    assert h.columns(rows) == [("n", ""), ("x", "s")]
    assert h.table(rows, "k").splitlines()[2:] == ["| a | 3 |  |", "| b | 10,000 | 1.50 |"]
    with pytest.raises(ValueError, match="'t'"):  # one column, two units: refused
        h.columns([h.Row("a", {"t": h.Figure(1.0, "us")}), h.Row("b", {"t": h.Figure(1.0, "s")})])


def test_alignment_follows_what_cells_hold() -> None:
    rows = [h.Row("a", {"n": h.Figure("**2.0**"), "w": h.Figure("harness 1, broker 2")}),
            h.Row("b", {"n": h.Figure("-"), "w": h.Figure(3.0)})]
    assert h.table(rows).splitlines()[1] == "|---|---:|---|"


def test_json_round_trip(tmp_path: Path) -> None:
    results = [_result(), h.Result("decode", "second table")]
    js, md = h.write(tmp_path / "new", "decode", results)
    assert js.name == "decode.json" and md.read_text() == h.markdown(results)
    back = h.read(js)
    assert back == results
    assert back[0].rows[0].figures["time"] == h.Figure(5.25, "ms", 5.0, 6.0)


def test_common_options() -> None:
    ap = h.options("doc", repeats=7)
    ap.add_argument("--pairs", type=int, default=3)
    a = ap.parse_args(["--quick", "--out", "x/y", "--pairs", "4"])
    assert (a.quick, a.repeats, a.out, a.pairs) == (True, 7, Path("x/y"), 4)
    assert ap.parse_args([]).out == Path("bench-results")
    # the help names a bench as it is run
    assert h._prog("/repo/benchmarks/shm.py") == "python -m benchmarks.shm"
    assert h._prog("/repo/scripts/other.py") is None


BURN = ("import sys, time\n"
        "t = time.process_time()\n"
        "while time.process_time() - t < 0.3: pass\n"
        "print('burnt', flush=True)\n"
        "sys.stdin.read()\n")


def test_tree_cpu_counts_a_living_child_that_burns() -> None:
    """A child (under a shell, so a grandchild of this process) burns 0.3 s of CPU and
    stays alive: the tree's CPU over the window holds it."""
    before = h.tree_cpu(os.getpid())
    child = subprocess.Popen(["sh", "-c", f'"{sys.executable}" -c "$0"; true', BURN],
                             stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert child.stdout is not None and child.stdout.readline() == "burnt\n"
        spent = h.tree_cpu(os.getpid()) - before
        assert spent >= 0.28
        # the shell's own tree holds it too: its child, alive, not yet reaped
        assert h.tree_cpu(child.pid) >= 0.28
        assert h.tree_cpu(child.pid, children=False) < 0.1  # the shell itself: no burn
    finally:
        child.communicate("", timeout=20)


def test_tree_cpu_counts_a_child_that_ended_in_the_window() -> None:
    before = h.tree_cpu(os.getpid())
    subprocess.run([sys.executable, "-c", BURN], input="", text=True, capture_output=True,
                   check=True, timeout=20)
    assert h.tree_cpu(os.getpid()) - before >= 0.28


def test_tree_cpu_of_a_process_gone_is_zero() -> None:
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait(timeout=20)
    assert h.tree_cpu(p.pid) == 0.0


def test_every_bench_runs_on_the_harness() -> None:
    """A bench takes the harness's options, writes through it, reads CPU only through it,
    runs as `python -m benchmarks.NAME`, and puts nothing on sys.path."""
    benches = sorted(p for p in BENCHES.glob("*.py") if p.stem not in NOT_BENCHES)
    assert len(benches) >= 19
    for path in benches:
        text = path.read_text(encoding="utf-8")
        assert "h.options(" in text and "h.write(" in text, path.name
        assert 'if __name__ == "__main__":' in text, path.name
    for path in BENCHES.glob("*.py"):
        text = path.read_text(encoding="utf-8")
        assert "sys.path" not in text, path.name
        assert path.stem == "harness" or ".cpu_times(" not in text, path.name


def test_bench_sh_runs_modules_that_exist() -> None:
    text = (REPO / "scripts" / "bench.sh").read_text(encoding="utf-8")
    modules = set(re.findall(r"-m benchmarks\.(\w+)", text))
    assert len(modules) >= 17
    assert all((BENCHES / f"{m}.py").is_file() for m in modules), modules
    assert "scripts/bench_" not in text
