"""Which pipeline `trapflow record` attaches to (trapflow.cli.attach.decide): one that
answers, one that is starting (waited for, a bounded time), never a stopped one, and never
the old run runs/latest still names while a new pipeline starts."""

from __future__ import annotations

from pathlib import Path

import pytest

from trapflow.cli.attach import Go, Look, Refuse, Wait, decide


def _look(**kw: object) -> Look:
    base: dict[str, object] = {"named": Path("runs/latest"), "target": Path("/w/runs/old"),
                               "is_link": True, "exists": True, "alive": False,
                               "status": None, "starting_beside": ()}
    return Look(**{**base, **kw})  # type: ignore[arg-type]


@pytest.mark.parametrize(("seen", "waited", "kind", "words"), [
    (_look(alive=True, status={"rig": None}), 0.0, Go, ""),
    (_look(), 0.0, Refuse, "no pipeline runs in runs/latest (-> /w/runs/old): its run has "
                           "stopped"),
    (_look(exists=False), 0.0, Refuse, "no run directory runs/latest"),
    (_look(alive=True), 0.0, Wait, "is starting; waiting for it (up to 30 s, --wait)"),
    (_look(alive=True), 30.0, Refuse, "no pipeline answered there within 30 s"),
    (_look(starting_beside=(Path("/w/runs/a"), Path("/w/runs/b"))), 1.0, Wait,
     "runs/latest names a stopped run (/w/runs/old) while a pipeline starts in /w/runs/b; "
     "waiting for runs/latest to name it"),
    (_look(is_link=False, named=Path("/w/runs/old"),
           starting_beside=(Path("/w/runs/b"),)), 0.0, Refuse, "its run has stopped"),
])
def test_record_attaches_only_to_a_running_pipeline(seen: Look, waited: float, kind: type,
                                                    words: str) -> None:
    verdict = decide(seen, waited, 30.0)
    assert isinstance(verdict, kind)
    if isinstance(verdict, Go):
        assert verdict.run_dir == seen.target  # pinned: runs/latest may move on
    else:
        assert words in verdict[0]
