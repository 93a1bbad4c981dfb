"""VO's results.jsonl keeps the precision VO has: a real pipeline run, its Rt rows integrated."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from tests.conftest import Pipeline, poll_for

pytestmark = pytest.mark.slow  # starts whole pipelines


def _m(rows: list[list[float]]) -> np.ndarray:
    out = np.eye(4)
    out[:3, :4] = np.asarray(rows, float)
    return out


@pytest.mark.timeout(120)
def test_integrated_rt_rows_give_the_workers_pose(spawn, run_dir: Path) -> None:
    """Regression: at `normalizer.decimals: 3` results.jsonl kept Rt to 5 decimals and the pose
    to 1 mm, and integrating Rt gave 8x VO's rotational drift. Composing the Rt rows of a real
    run, from its first pose, must give every later pose the worker wrote, within 1e-6."""
    p: Pipeline = spawn(["--workers", "vo=1", "--moving", "--size", "320x240", "--rate", "15"],
                        run_dir)

    def vo_rows() -> list[dict[str, Any]]:
        return [r["stereo_vo"] for r in p.results() if "stereo_vo" in r]

    poll_for(lambda: len(vo_rows()) >= 40, 60, what="40 VO results")
    code, _, err = p.stop()
    assert code == 0, err
    rows = vo_rows()
    steps = [r for r in rows[1:] if "Rt" in r]
    assert len(steps) >= 20, f"expected 20+ ok VO results, got {len(steps)} of {len(rows)}"
    acc = _m(rows[0]["pose"])
    worst = 0.0
    for r in rows[1:]:
        if "Rt" in r:
            acc = acc @ _m(r["Rt"])
        worst = max(worst, float(np.abs(acc[:3, :4] - _m(r["pose"])[:3, :4]).max()))
    assert worst <= 1e-6, f"integrated Rt strays {worst:.2g} from the worker's pose"
    # The run moved and turned, so the comparison means something.
    travelled = np.linalg.norm(_m(rows[-1]["pose"])[:3, 3] - _m(rows[0]["pose"])[:3, 3])
    assert travelled > 0.05, f"the rig moved only {travelled:.3f} m"
    assert max(abs(s["Rt"][0][1]) for s in steps) > 1e-4, "no step turned"
