"""End to end with real processes: a motion-gated pool on the synthetic default world."""

from __future__ import annotations

import json
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
