"""`trapflow export camtrapdp` on a real run with tracks and events: the package validates
against the official Camtrap DP profile and table schemas, and its rows say what the run's
tracks.jsonl, results.jsonl and event folders say.

The official schemas are read from the real-data kit (camtrap-dp/<version>/, as the Camtrap
DP repository publishes them), never vendored: that part skips when the kit is absent
(docs/conformance.md lists what was checked). Frictionless checks the package's structure in
any case (every table well-formed, every declared file there).
"""

from __future__ import annotations

import csv
import datetime as dt
import json
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import cv2
import pytest

from tests.conformance.conftest import kit_path, realdata_root
from tests.conftest import REPO, only_pools, write_config

frictionless = pytest.importorskip("frictionless", reason="frictionless (test extra) missing")
W, H = 320, 240
CUT = 0.5  # export.min_confidence's default


def read_csv(path: Path) -> list[dict[str, str]]:
    with path.open(newline="", encoding="utf-8") as fh:
        return list(csv.DictReader(fh))


def jsonl(path: Path, kind: str) -> list[dict[str, Any]]:
    return [x[kind] for x in map(json.loads, path.read_text().splitlines()) if kind in x]


def iso(t_s: float) -> str:
    return dt.datetime.fromtimestamp(t_s, dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")


def utc_s(label: str) -> float:
    return dt.datetime.strptime(label, "%Y-%m-%d %H:%M:%S.%f").replace(
        tzinfo=dt.timezone.utc).timestamp()


def export(run_dir: Path, out: Path, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "trapflow", "export", "camtrapdp", str(run_dir),
                           str(out), *args], cwd=REPO, capture_output=True, text=True,
                          timeout=60)


def check_structure(out: Path) -> dict[str, Any]:
    """Frictionless on the package with its schemas inferred (needs no kit)."""
    pkg: dict[str, Any] = json.loads((out / "datapackage.json").read_text())
    local = {**pkg, "resources": [{k: v for k, v in r.items() if k not in ("schema", "profile")}
                                  for r in pkg["resources"]]}
    local.pop("profile")
    report = frictionless.Package(local, basepath=str(out)).validate()
    assert report.valid, report.flatten(["rowNumber", "fieldName", "type", "note"])
    return pkg


def check_official(out: Path) -> None:
    """The official profile (its Camtrap DP part, as JSON Schema; frictionless checks the Data
    Package part) and table schemas of the package's version, from the kit."""
    import jsonschema
    from referencing import Registry, Resource
    from referencing.jsonschema import DRAFT4

    pkg = json.loads((out / "datapackage.json").read_text())
    version = pkg["profile"].split("/camtrap-dp/")[1].split("/")[0]
    kit = kit_path(realdata_root(), "camtrap-dp", version)
    profile = json.loads((kit / "camtrap-dp-profile.json").read_text())
    # allOf[0] is the Data Package schema by URL, allOf[1] Camtrap DP's own rules; its spatial
    # field refers to GeoJSON by URL: frictionless' own copy stands in (no network here).
    assert profile["allOf"][0] == {"$ref": "https://specs.frictionlessdata.io/schemas/"
                                           "data-package.json"}
    geojson = json.loads((Path(frictionless.__file__).parent / "assets" / "profiles" /
                          "geojson.json").read_text())

    def offline(uri: str) -> Resource[Any]:
        raise LookupError(f"the profile refers to {uri}, which this test cannot fetch")

    registry: Registry[Any] = Registry(retrieve=offline).with_resource(
        "http://json.schemastore.org/geojson.json",
        Resource.from_contents(geojson, default_specification=DRAFT4))
    validator = jsonschema.Draft4Validator(
        {**profile, "allOf": [profile["allOf"][1]]}, registry=registry,
        format_checker=jsonschema.Draft4Validator.FORMAT_CHECKER)
    errors = [f"{list(e.absolute_path)}: {e.message}" for e in validator.iter_errors(pkg)]
    assert not errors, errors

    local = {**pkg, "resources": [
        {**r, "schema": json.loads((kit / Path(r["schema"]).name).read_text())}
        for r in pkg["resources"]]}
    local.pop("profile")
    report = frictionless.Package(local, basepath=str(out)).validate()
    assert report.valid, report.flatten(["rowNumber", "fieldName", "type", "note"])


TAXA = {"crab": "Cancer pagurus"}  # what the test's --taxon gives


def check_event_rows(obs: list[dict[str, str]], tracks: list[dict[str, Any]],
                     cut: float) -> None:
    """One event-level row per track at or above the cut, its fields the track's."""
    events = {o["eventID"]: o for o in obs if o["observationLevel"] == "event"}
    kept = [t for t in tracks if t["best_confidence"] >= cut]
    assert sorted(events) == sorted(f"track-{t['id']}" for t in kept)
    for t in kept:
        o = events[f"track-{t['id']}"]
        assert (o["individualID"], o["count"], o["mediaID"]) == (str(t["id"]), "1", "")
        assert (o["eventStart"], o["eventEnd"]) == (iso(t["first_s"]), iso(t["last_s"]))
        # The detector also knows scallops; only crab is given a taxon (--taxon), so a track
        # labelled otherwise is exported unclassified.
        name = TAXA.get(t["label"], "")
        assert (o["scientificName"], o["observationType"]) == (
            name, "animal" if name else "unclassified")
        assert float(o["classificationProbability"]) == pytest.approx(t["best_confidence"])
        assert o["classificationMethod"] == "machine"
        for key, field in (("position_radius_m", "individualPositionRadius"),
                           ("position_angle_deg", "individualPositionAngle"),
                           ("speed_m_s", "individualSpeed")):
            assert (float(o[field]) if o[field] else None) == t.get(key), (key, o, t)
        if "length_m" in t:
            assert f"length_m:{t['length_m']:.3f}" in o["observationTags"].split("|")
            assert f"length {t['length_m']:.3f} m" in o["observationComments"]
        else:
            assert o["observationTags"] == ""


@pytest.mark.slow  # starts a whole pipeline
@pytest.mark.timeout(300)
def test_package_of_a_run_with_tracks_and_events(spawn, run_dir: Path, tmp_path: Path) -> None:
    cfg = write_config(tmp_path / "events.yaml", {
        # Every pair to mono: media.csv dates an image by its pair's result (a pair the
        # gate withheld has none, and only mono runs here).
        "pools": only_pools({"mono": {"count": 1, "gate": "always"}}),
        "events": {"enabled": True, "pre_s": 0.4, "post_s": 0.6,
                   "triggers": [{"algorithm": "mono_ir", "label": "crab",
                                 "min_confidence": 0.3}]}})
    p = spawn(["--config", str(cfg), "--size", f"{W}x{H}", "--rate", "5", "--duration", "10"],
              run_dir)
    code, _, err = p.wait(150)
    assert code == 0, err
    assert list((run_dir / "events").glob("*/event.json")), "no event was captured"
    tracks = jsonl(run_dir / "tracks.jsonl", "track")
    lines = jsonl(run_dir / "results.jsonl", "mono_ir")
    assert tracks and any("length_m" in t and "speed_m_s" in t for t in tracks), tracks
    assert any(t["label"] == "crab" for t in tracks), tracks
    # The run's files tell one story: ledger, results, tracks and counts agree.
    res = subprocess.run([sys.executable, "-m", "trapflow", "check", str(run_dir)], cwd=REPO,
                         capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stdout + res.stderr

    out = tmp_path / "pkg"
    res = export(run_dir, out, "--latitude", "50.35", "--longitude", "-4.14", "--depth", "12.5",
                 "--location-name", "Plymouth Sound", "--setup-by", "diver",
                 "--taxon", "crab=Cancer pagurus")
    assert res.returncode == 0, res.stderr
    pkg = check_structure(out)
    assert pkg["profile"].endswith("camtrap-dp-profile.json")
    assert [r["name"] for r in pkg["resources"]] == ["deployments", "media", "observations"]
    assert pkg["project"]["observationLevel"] == ["event", "media"]
    assert pkg["taxonomic"] == [{"scientificName": "Cancer pagurus"}]
    (dep,) = read_csv(out / "deployments.csv")
    assert (float(dep["latitude"]), float(dep["longitude"]), float(dep["cameraDepth"])) == \
        (50.35, -4.14, 12.5)
    assert dep["deploymentID"] == run_dir.name and dep["locationName"] == "Plymouth Sound"

    # Media: every left image of every event whose pair has a result (its capture time comes
    # from it: a pair still on its way at the stop has none), the file itself in the package.
    media = read_csv(out / "media.csv")
    with_result = {x["seq"] for x in lines}
    jpgs = sorted(j for j in (run_dir / "events").glob("*/left/*.jpg")
                  if int(j.stem) in with_result)
    assert len(media) == len({j.stem for j in jpgs}) > 0  # once per pair
    for m in media:
        img = cv2.imread(str(out / m["filePath"]))
        assert img is not None and img.shape[:2] == (H, W)
    seq_of = {m["mediaID"]: int(Path(m["fileName"]).stem) for m in media}

    obs = read_csv(out / "observations.csv")
    check_event_rows(obs, tracks, CUT)

    # Blanks: exactly the images without a box at or above the cut.
    strong = {x["seq"] for x in lines if len(x["box"]) == 4 and x["confidence"] >= CUT}
    blanks = {o["mediaID"] for o in obs if o["observationType"] == "blank"}
    assert blanks == {m for m, s in seq_of.items() if s not in strong}
    assert all(o["observationLevel"] == "media" and not o["scientificName"]
               for o in obs if o["observationType"] == "blank")

    # Media-level rows: the best frame of each track, linked to its event, its box the best.
    frames = [o for o in obs if o["observationLevel"] == "media" and o["observationType"]
              != "blank"]
    assert frames, "no track's best frame fell in an event"
    by_track = {f"track-{t['id']}": t for t in tracks}
    for o in frames:
        t = by_track[o["eventID"]]
        assert o["individualID"] == str(t["id"])
        seq = seq_of[o["mediaID"]]
        (line,) = [x for x in lines if x["seq"] == seq and x["box"] == t["best_box"]
                   and x["confidence"] == t["best_confidence"]]
        assert t["first_s"] - 0.002 <= utc_s(line["timestamp"]) <= t["last_s"] + 0.002
        x1, y1, x2, y2 = line["box"]
        assert float(o["bboxX"]) * W == pytest.approx(max(x1, 0), abs=0.01)
        assert float(o["bboxY"]) * H == pytest.approx(max(y1, 0), abs=0.01)
        assert float(o["bboxWidth"]) * W == pytest.approx(min(x2, W) - max(x1, 0), abs=0.01)
        assert float(o["bboxHeight"]) * H == pytest.approx(min(y2, H) - max(y1, 0), abs=0.01)
    assert len({o["eventID"] for o in frames}) == len(frames)  # one best frame per track
    check_official(out)

    # The cut: a higher one keeps fewer tracks and turns more images blank.
    high = max(t["best_confidence"] for t in tracks)
    res = export(run_dir, tmp_path / "cut", "--latitude", "0", "--longitude", "0",
                 "--taxon", "crab=Cancer pagurus", "--min-confidence", str(high))
    assert res.returncode == 0, res.stderr
    cut_obs = read_csv(tmp_path / "cut" / "observations.csv")
    check_event_rows(cut_obs, tracks, high)
    assert {o["mediaID"] for o in cut_obs if o["observationType"] == "blank"} >= blanks
    check_official(tmp_path / "cut")

    # A run without tracks.jsonl (tracking off): one media-level row per box at the cut.
    bare = tmp_path / "bare"
    bare.mkdir()
    shutil.copy(run_dir / "results.jsonl", bare)
    shutil.copytree(run_dir / "events", bare / "events")
    res = export(bare, tmp_path / "bare-pkg", "--latitude", "0", "--longitude", "0")
    assert res.returncode == 0, res.stderr
    bare_obs = read_csv(tmp_path / "bare-pkg" / "observations.csv")
    assert all(o["observationLevel"] == "media" for o in bare_obs)
    boxes = sorted((x["seq"], x["confidence"]) for x in lines if len(x["box"]) == 4
                   and x["confidence"] >= CUT and x["seq"] in seq_of.values())
    assert sorted((seq_of[o["mediaID"]], float(o["classificationProbability"]))
                  for o in bare_obs if o["observationType"] != "blank") == boxes
    assert all(o["observationType"] == "unclassified" for o in bare_obs
               if o["observationType"] != "blank")
    check_official(tmp_path / "bare-pkg")


@pytest.fixture
def tiny_run(tmp_path: Path) -> Path:
    """A run directory of one result line: enough for the checks made before reading it."""
    run = tmp_path / "run"
    run.mkdir()
    (run / "results.jsonl").write_text(json.dumps({"mono_ir": {
        "timestamp": "2026-11-25 10:00:00.000", "seq": 0, "label": "none", "confidence": 0,
        "box": [], "v": 2}}) + "\n")
    return run


@pytest.mark.parametrize(("args", "message"), [
    ([], "latitude and longitude"),
    (["--latitude", "91", "--longitude", "0"], "latitude: expected a number in -90..90"),
    (["--latitude", "0", "--longitude", "0", "--taxon", "crab"], "expected LABEL=NAME"),
    (["--latitude", "0", "--longitude", "0", "--depth", "-3"], "depth: expected a number"),
    (["--latitude", "0", "--longitude", "0", "--min-confidence", "1.5"], "--min-confidence"),
    (["--latitude", "0", "--longitude", "0", "--config", "missing.yaml"], "missing.yaml"),
])
def test_export_refuses_bad_input(tiny_run: Path, tmp_path: Path, args: list[str],
                                  message: str) -> None:
    res = export(tiny_run, tmp_path / "pkg", *args)
    assert res.returncode == 2 and message in res.stderr, res.stderr
    assert not (tmp_path / "pkg").exists()


def test_export_of_a_run_without_events_or_tracks(tiny_run: Path, tmp_path: Path) -> None:
    """No images and no tracks: a valid package with one deployment and nothing observed."""
    res = export(tiny_run, tmp_path / "pkg", "--latitude", "0", "--longitude", "0")
    assert res.returncode == 0, res.stderr
    check_structure(tmp_path / "pkg")
    assert read_csv(tmp_path / "pkg" / "observations.csv") == []
    check_official(tmp_path / "pkg")
