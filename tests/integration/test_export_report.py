"""`trapflow report RUN_DIR` on the directory of a real run: the page is one self-contained
HTML file whose tables and charts say what the run's own files say."""

from __future__ import annotations

import datetime as dt
import json
import subprocess
import sys
from collections import Counter
from html.parser import HTMLParser
from pathlib import Path

import pytest

from tests.conftest import REPO, Pipeline
from trapflow.wire.pool_counters import LEDGER_STATES

pytestmark = pytest.mark.slow  # starts whole pipelines


class Page(HTMLParser):
    """Tables as lists of rows, polylines with their attributes, and every URL referenced."""

    def __init__(self) -> None:
        super().__init__()
        self.tables: list[list[list[str]]] = []
        self.polylines: list[dict[str, str]] = []
        self.bars: list[dict[str, str]] = []
        self.urls: list[str] = []
        self._cell: list[str] | None = None

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        a = {k: v or "" for k, v in attrs}
        self.urls += [v for k, v in a.items() if k in ("src", "href")]
        if tag == "table":
            self.tables.append([])
        elif tag == "tr":
            self.tables[-1].append([])
        elif tag in ("td", "th"):
            self._cell = []
        elif tag == "polyline":
            self.polylines.append(a)
        elif tag == "rect" and a.get("class") == "bar":
            self.bars.append(a)

    def handle_endtag(self, tag: str) -> None:
        if tag in ("td", "th") and self._cell is not None:
            self.tables[-1][-1].append("".join(self._cell))
            self._cell = None

    def handle_data(self, data: str) -> None:
        if self._cell is not None:
            self._cell.append(data)

    def table(self, *head: str) -> list[list[str]]:
        """The rows of the table whose header starts with these cells."""
        (found,) = [t for t in self.tables if tuple(t[0][:len(head)]) == head]
        return found[1:]


@pytest.mark.timeout(150)
def test_report_of_a_real_run(spawn, run_dir: Path) -> None:
    p: Pipeline = spawn(["--workers", "mono=1,vo=1", "--size", "320x240", "--rate", "5",
                         "--moving", "--duration", "12"], run_dir)
    code, _, err = p.wait(120)
    assert code == 0, err
    out = run_dir.parent / "page.html"
    res = subprocess.run([sys.executable, "-m", "trapflow", "report", str(run_dir), "-o",
                          str(out)], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stderr
    page = Page()
    page.feed(out.read_text())
    assert page.urls == []  # self-contained: nothing to fetch

    lines = [json.loads(x) for x in (run_dir / "results.jsonl").read_text().splitlines()]
    # Detections per class per hour, counted here from the lines themselves.
    want = Counter((x["mono_ir"]["timestamp"][:13] + ":00", x["mono_ir"]["label"])
                   for x in lines if "mono_ir" in x and x["mono_ir"]["label"] != "none")
    head, *rows = next(t for t in page.tables if t[0][0] == "hour (UTC)")  # the first
    assert head[0] == "hour (UTC)" and head[-1] == "all" and head[1] != "label"
    got = Counter({(r[0], c): int(v) for r in rows for c, v in zip(head[1:-1], r[1:-1],
                                                                    strict=True) if int(v)})
    assert got == want and sum(want.values()) > 0

    # Drops and losses: the ledger's numbers, pool by pool.
    ledger = json.loads((run_dir / "ledger.json").read_text())
    head, *rows = next(t for t in page.tables if t[0][:2] == ["pool", "processed"])
    key = {label: k for k, label in LEDGER_STATES}
    pools = {r[0]: {key[h]: int(v) for h, v in zip(head[1:], r[1:], strict=True)} for r in rows}
    assert set(pools) == set(ledger["pools"])
    for name, q in ledger["pools"].items():
        assert pools[name] == {k: q.get(k, 0) for k in pools[name]}, name
        assert {k for k, _label in LEDGER_STATES if q.get(k)} <= set(pools[name]), name

    # Charts: a rate series per pool, the VO path with one point per ok pose.
    series = {pl["data-name"]: int(pl["data-points"]) for pl in page.polylines}
    ok = sum(1 for x in lines if "stereo_vo" in x and x["stereo_vo"]["ok"])
    assert series["left camera"] == ok > 0
    assert {"mono_ir", "stereo_vo"} <= set(series)
    check_observations(page, run_dir)

    # The run itself (issue 22, item 11): run.json, as the supervisor wrote it, on the page.
    meta = json.loads((run_dir / "run.json").read_text())
    assert 12 <= meta["duration_s"] < 120
    assert meta["config"]["pools"].keys() == {"mono", "vo"}
    assert meta["config"]["source"]["size"] == "320x240"
    assert meta["rig"]["calib"] and meta["versions"]["trapflow"]
    run = {r[0]: r[1] for r in page.table("run")}
    assert f"{meta['duration_s']} s" in run["ran"]
    assert f"digest {meta['config']['digest']}" in run["config"]
    assert meta["rig"]["calib"] in run["rig"]
    assert f"trapflow {meta['versions']['trapflow']}" in run["versions"]


def check_observations(page: Page, run_dir: Path) -> None:
    """Visits and MaxN per label per hour as counts.jsonl has them, and a length-frequency
    histogram per label holding every measured track of tracks.jsonl."""
    counts = [json.loads(x)["counts"] for x in (run_dir / "counts.jsonl").read_text()
              .splitlines()]
    want: dict[tuple[str, str], list[int]] = {}
    for c in counts:
        hour = dt.datetime.fromtimestamp(c["start_s"], dt.timezone.utc).strftime(
            "%Y-%m-%d %H:00")
        for lb in c["labels"]:
            v = want.setdefault((hour, lb["label"]), [0, 0])
            v[:] = [v[0] + lb["visits"], max(v[1], lb["max_n"])]
    got = {(r[0], r[1]): [int(r[2]), int(r[3])]
           for r in page.table("hour (UTC)", "label", "visits", "MaxN")}
    assert got == want and any(v[0] for v in want.values()), (got, want)

    tracks = [json.loads(x)["track"] for x in (run_dir / "tracks.jsonl").read_text()
              .splitlines()]
    lengths = Counter(t["label"] for t in tracks if "length_m" in t)
    assert lengths, "no track was measured"
    bars = Counter[str]()
    for b in page.bars:
        bars[b["data-label"]] += int(b["data-count"])
    assert bars == lengths
    for t in tracks:  # each length lies in a bin of its label holding at least one track
        if "length_m" in t:
            assert any(float(b["data-from"]) - 5e-4 <= t["length_m"] < float(b["data-to"])
                       + 5e-4 and int(b["data-count"]) for b in page.bars
                       if b["data-label"] == t["label"])
    rows = {r[0]: int(r[1]) for r in page.table("label", "tracks measured")}
    assert rows == dict(lengths)


@pytest.mark.parametrize(("make", "message"), [
    (lambda d: None, "expected"),  # no run directory at all
    (lambda d: d.mkdir(), "results.jsonl"),  # a directory without results
])
def test_report_refuses_what_is_no_run(tmp_path: Path, make: object, message: str) -> None:
    run = tmp_path / "run"
    make(run)  # type: ignore[operator]
    res = subprocess.run([sys.executable, "-m", "trapflow", "report", str(run)], cwd=REPO,
                         capture_output=True, text=True, timeout=60)
    assert res.returncode == 2
    assert message in res.stderr and "--run-dir" in res.stderr
