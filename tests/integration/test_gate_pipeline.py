"""End to end with real processes: a motion-gated pool on the synthetic default world."""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path

import pytest

from tests.conftest import Pipeline, write_config

pytestmark = pytest.mark.slow  # starts a whole pipeline


@pytest.mark.timeout(90)
def test_a_gated_pool_gets_fewer_pairs_and_the_ledger_counts_them_gated(
        spawn, run_dir: Path) -> None:
    """The default world (crabs walk in after 3 s) with mono gated: the empty water before
    them is withheld from mono and counted gated, nothing is lost, and VO (never gated)
    gets every pair."""
    cfg = write_config(run_dir.parent / "gated.yaml", {"pools": {"mono": {"gate": "motion"}}})
    p: Pipeline = spawn(["--config", str(cfg), "--duration", "10"], run_dir)
    code, out, err = p.wait(75)
    assert code == 0, err
    pools = json.loads((run_dir / "ledger.json").read_text())["pools"]
    mono, vo = pools["mono"], pools["vo"]
    assert mono["gated"] > 0 and vo["gated"] == 0
    assert all(pool["lost"] == 0 for pool in pools.values()), pools
    assert mono["processed"] < vo["processed"]
    assert f"gated {mono['gated']}" in out  # the totals line says it too
    assert not p.leftovers()


STILL_ANIMAL = "tests.integration.gate_plugins:StillAnimal"
NO_ANIMAL = "tests.integration.gate_plugins:NoAnimal"


def _gated_mono(plugin: str, source: Mapping[str, object], vo: int = 1,
                gate: dict[str, float] | None = None, **extra: object) -> dict[str, object]:
    """mono gated (keep-alive 1 s, no hold, no pre-roll, no busy rate, and `gate`), the other
    recognisers off."""
    return {"source": {"kind": "synthetic", "rate_hz": 10.0, **source},
            "pools": {"mono": {"plugin": plugin, "gate": "motion"}, "vo": {"count": vo},
                      "stereo": {"count": 0}, "tags": {"count": 0}},
            "gate": {"keepalive_s": 1.0, "hold_s": 0.0, "pre_roll": 0, "busy_rate_hz": 0.0,
                     **(gate or {})},
            **extra}


@pytest.mark.timeout(90)
@pytest.mark.parametrize(("tracking", "busy"), [(True, 0.0), (False, 0.0), (True, 4.0)])
def test_a_live_track_holds_the_gate_open(spawn, run_dir: Path, tracking: bool,
                                          busy: float) -> None:
    """Still water (no animal, no snow: the gate never sees motion) and a detector that sees
    a motionless crab in every pair it gets: its track, confirmed by the second keep-alive
    pair, is told to the broker by the normalizer, and from then on mono gets every pair
    while the track lives. Without tracking (observe off) mono gets only the keep-alive.
    With a busy rate of 4 pairs/s, mono gets 4 of every 10 pairs while the track lives
    (it stays alive on them), the rest counted gated."""
    still = {"options": {"density": 0.0, "snow": 0.0}}
    cfg = write_config(run_dir.parent / "track.yaml", _gated_mono(
        STILL_ANIMAL, still, vo=0, gate={"busy_rate_hz": busy}, observe={"enabled": tracking}))
    p: Pipeline = spawn(["--config", str(cfg), "--duration", "8"], run_dir)
    code, _out, err = p.wait(75)
    assert code == 0, err
    ledger = json.loads((run_dir / "ledger.json").read_text())
    mono, produced = ledger["pools"]["mono"], ledger["produced"]
    assert mono["lost"] == 0 and produced >= 40, ledger
    if busy:  # 4 of 10 once the track lives (a keep-alive alone would be 1 of 10)
        assert 0.25 * produced <= mono["processed"] <= 0.5 * produced, ledger
        assert mono["gated"] >= 0.4 * produced, ledger  # withheld: counted, never lost
    elif tracking:  # all but the first second or so (1 s keep-alive, 2 hits to confirm)
        assert mono["processed"] >= 0.6 * produced, ledger
    else:  # about one pair a second
        assert mono["processed"] <= 0.25 * produced and mono["gated"] > 0, ledger
    assert not p.leftovers()


@pytest.mark.timeout(120)
def test_a_moving_rig_turns_the_gate_off(spawn, run_dir: Path) -> None:
    """A moving rig changes every pixel: capture's detector learns each view afresh and sees
    no motion, so without VO's word the gated pool would get only the keep-alive. VO sees
    the rig move, the normalizer tells the broker, the gate feeds every pair from then on
    and says so in one INFO line."""
    cfg = write_config(run_dir.parent / "moving.yaml",
                       _gated_mono(NO_ANIMAL, {"moving": True}))
    p: Pipeline = spawn(["--config", str(cfg), "--duration", "10"], run_dir)
    code, _out, err = p.wait(100)
    assert code == 0, err
    ledger = json.loads((run_dir / "ledger.json").read_text())
    mono, vo = ledger["pools"]["mono"], ledger["pools"]["vo"]
    assert vo["processed"] > 20, ledger  # VO ran (it is never gated)
    # Gated only until VO has seen the rig move (a few pairs, plus VO's own lag).
    assert mono["gated"] <= 0.3 * ledger["produced"], ledger
    log = (run_dir / "trapflow.log").read_text()
    assert log.count("motion gate off: the rig moves") == 1, log[-2000:]
    assert not p.leftovers()


@pytest.mark.timeout(90)
def test_duty_cycling_drops_capture_to_the_idle_rate_on_still_water(spawn, run_dir: Path
                                                                    ) -> None:
    """Still water with duty cycling on (idle after 1 s at 2 pairs/s): capture says so in
    one INFO line and, after the first second at 10 pairs/s, sends about 2 pairs a second;
    without it the same run sends about 10."""
    still = {"options": {"density": 0.0, "snow": 0.0}}
    cfg = write_config(run_dir.parent / "duty.yaml", _gated_mono(
        NO_ANIMAL, still, vo=0, gate={"idle_after_s": 1.0, "idle_rate_hz": 2.0}))
    p: Pipeline = spawn(["--config", str(cfg), "--duration", "8"], run_dir)
    code, _out, err = p.wait(75)
    assert code == 0, err
    produced = json.loads((run_dir / "ledger.json").read_text())["produced"]
    # 8 s: about 10 pairs in the first second, then 2 a second (about 24); at full rate 80.
    assert 12 <= produced <= 40, produced
    log = (run_dir / "trapflow.log").read_text()
    assert log.count("duty cycling: 2 pairs/s after 1 s without motion") == 1, log[-2000:]
    assert not p.leftovers()
