"""`trapflow export camtrapdp` on a real run with events: the package is a valid Frictionless
data package whose rows say what the run's event folders and results say.

Validation against the official Camtrap DP table schemas runs when they are in the
real-data kit (camtrap-dp/<version>/, as the Camtrap DP repository publishes them); the
schemas are not vendored into this repository, and no installable package ships them
(docs/conformance.md lists what was checked). Frictionless checks the package's structure
in any case (every table well-formed, every declared file there).
"""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import cv2
import pytest

from tests.conformance.conftest import kit_path, realdata_root
from tests.conftest import REPO, Pipeline, only_pools, write_config

pytestmark = pytest.mark.slow  # starts whole pipelines

frictionless = pytest.importorskip("frictionless", reason="frictionless (test extra) missing")
W, H = 320, 240


def read_csv(path: Path) -> list[dict[str, str]]:
    with path.open(newline="", encoding="utf-8") as fh:
        return list(csv.DictReader(fh))


@pytest.fixture(scope="module")
def run_with_events(tmp_path_factory: pytest.TempPathFactory) -> Path:
    work = tmp_path_factory.mktemp("ctdp")
    run_dir = work / "run"
    cfg = write_config(work / "events.yaml", {
        "pools": only_pools({"mono": {"count": 1}}),
        "events": {"enabled": True, "pre_s": 0.4, "post_s": 0.6,
                   "triggers": [{"algorithm": "mono_ir", "label": "crab",
                                 "min_confidence": 0.3}]}})
    p = Pipeline(["--config", str(cfg), "--size", f"{W}x{H}", "--rate", "5", "--duration", "10"],
                 run_dir)
    try:
        out, err = p.proc.communicate(timeout=120)
    finally:
        p.kill_all()
    assert p.proc.returncode == 0, err
    assert list((run_dir / "events").glob("*/event.json")), "no event was captured"
    return run_dir


def export(run_dir: Path, out: Path, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "trapflow", "export", "camtrapdp", str(run_dir),
                           str(out), *args], cwd=REPO, capture_output=True, text=True,
                          timeout=60)


@pytest.mark.timeout(180)
def test_package_of_a_run_with_events(run_with_events: Path, tmp_path: Path) -> None:
    out = tmp_path / "pkg"
    res = export(run_with_events, out, "--latitude", "50.35", "--longitude", "-4.14",
                 "--depth", "12.5", "--location-name", "Plymouth Sound", "--setup-by", "diver",
                 "--taxon", "crab=Cancer pagurus")
    assert res.returncode == 0, res.stderr
    pkg = json.loads((out / "datapackage.json").read_text())
    assert pkg["profile"].endswith("camtrap-dp-profile.json")
    assert [r["name"] for r in pkg["resources"]] == ["deployments", "media", "observations"]

    # Frictionless: every table well-formed (schemas inferred; the official ones are remote).
    local = {**pkg, "resources": [{k: v for k, v in r.items() if k not in ("schema", "profile")}
                                  for r in pkg["resources"]]}
    local.pop("profile")
    report = frictionless.Package(local, basepath=str(out)).validate()
    assert report.valid, report.flatten(["rowNumber", "fieldName", "type", "note"])

    (dep,) = read_csv(out / "deployments.csv")
    assert (float(dep["latitude"]), float(dep["longitude"]), float(dep["cameraDepth"])) == \
        (50.35, -4.14, 12.5)
    assert dep["deploymentID"] == run_with_events.name and dep["locationName"] == "Plymouth Sound"

    # Media: every left image of every event, the file itself in the package.
    media = read_csv(out / "media.csv")
    jpgs = sorted((run_with_events / "events").glob("*/left/*.jpg"))
    assert len(media) == len(jpgs) > 0
    for m in media:
        img = cv2.imread(str(out / m["filePath"]))
        assert img is not None and img.shape[:2] == (H, W)
        assert m["deploymentID"] == dep["deploymentID"] and m["fileMediatype"] == "image/jpeg"
    by_id = {m["mediaID"]: m for m in media}

    # Observations: each crab box of those images, normalized to the image, top-left corner.
    lines = [json.loads(x) for x in (run_with_events / "results.jsonl").read_text().splitlines()]
    seqs = {int(p.stem) for p in jpgs}
    boxes: dict[int, list[dict[str, Any]]] = {}
    for x in lines:
        b = x.get("mono_ir")
        if b and b["seq"] in seqs and len(b["box"]) == 4:
            boxes.setdefault(b["seq"], []).append(b)
    obs = read_csv(out / "observations.csv")
    assert len(obs) == sum(len(v) for v in boxes.values()) > 0
    for o in obs:
        seq = int(Path(by_id[o["mediaID"]]["fileName"]).stem)
        x1, y1, x2, y2 = next(b["box"] for b in boxes[seq]
                              if abs(float(o["bboxX"]) * W - max(b["box"][0], 0)) < 0.01
                              and abs(float(o["bboxY"]) * H - max(b["box"][1], 0)) < 0.01)
        assert float(o["bboxWidth"]) * W == pytest.approx(min(x2, W) - max(x1, 0), abs=0.01)
        assert float(o["bboxHeight"]) * H == pytest.approx(min(y2, H) - max(y1, 0), abs=0.01)
        assert o["observationLevel"] == "media" and o["classificationMethod"] == "machine"
        assert o["scientificName"] == "Cancer pagurus" and o["observationType"] == "animal"
        assert 0 < float(o["classificationProbability"]) <= 1
    assert pkg["taxonomic"] == [{"scientificName": "Cancer pagurus"}]


@pytest.mark.timeout(120)
def test_package_validates_against_the_official_schemas(run_with_events: Path,
                                                        tmp_path: Path) -> None:
    """The official Camtrap DP table schemas, read from the real-data kit when it has them."""
    out = tmp_path / "pkg"
    assert export(run_with_events, out, "--latitude", "50.35", "--longitude", "-4.14"
                  ).returncode == 0
    pkg = json.loads((out / "datapackage.json").read_text())
    version = pkg["profile"].split("/camtrap-dp/")[1].split("/")[0]
    schemas = kit_path(realdata_root(), "camtrap-dp", version)
    local = {**pkg, "resources": [
        {**r, "schema": json.loads((schemas / Path(r["schema"]).name).read_text())}
        for r in pkg["resources"]]}
    local.pop("profile")
    report = frictionless.Package(local, basepath=str(out)).validate()
    assert report.valid, report.flatten(["rowNumber", "fieldName", "type", "note"])


@pytest.mark.parametrize(("args", "message"), [
    ([], "latitude and longitude"),
    (["--latitude", "91", "--longitude", "0"], "latitude: expected a number in -90..90"),
    (["--latitude", "0", "--longitude", "0", "--taxon", "crab"], "expected LABEL=NAME"),
    (["--latitude", "0", "--longitude", "0", "--depth", "-3"], "depth: expected a number"),
])
def test_export_refuses_bad_metadata(run_with_events: Path, tmp_path: Path,
                                     args: list[str], message: str) -> None:
    res = export(run_with_events, tmp_path / "pkg", *args)
    assert res.returncode == 2 and message in res.stderr, res.stderr
    assert not (tmp_path / "pkg").exists()
