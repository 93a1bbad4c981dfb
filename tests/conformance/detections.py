"""For the detector conformance tests: trapflow's detector on one image, and the comparison."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from trapflow_workers.crab_detector import CrabDetector

from trapflow.testing.kit import make_context, make_pair

# (label, confidence, (x1, y1, x2, y2) in image pixels)
Det = tuple[str, float, tuple[float, float, float, float]]

BOX_PX, SCORE = 1.0, 0.005  # the bounds: within 1 px and 0.005 confidence


def trapflow_detections(model: Path, image: np.ndarray, **params: Any) -> list[Det]:
    """What trapflow's mono detector reports for `image` (BGR) with `params` on `model`."""
    det = CrabDetector()
    det.configure({"model": str(model), "providers": ["cpu"], **params}, make_context(pool="mono"))
    out = det.process(make_pair(image)).detections
    return [(d.label, d.confidence, d.box) for d in out]


def assert_same(got: list[Det], want: list[Det], what: str) -> None:
    """Same count and labels in the same order, boxes within BOX_PX, scores within SCORE."""
    assert len(got) == len(want), f"{what}: {len(got)} detections, expected {len(want)}"
    assert [g[0] for g in got] == [w[0] for w in want], f"{what}: labels differ"
    np.testing.assert_allclose(
        [g[1] for g in got], [w[1] for w in want], atol=SCORE, err_msg=f"{what}: confidence"
    )
    np.testing.assert_allclose(
        np.reshape([g[2] for g in got], (-1, 4)),
        np.reshape([w[2] for w in want], (-1, 4)),
        atol=BOX_PX,
        err_msg=f"{what}: boxes",
    )


def differ(got: list[Det], want: list[Det]) -> bool:
    """True when assert_same would fail."""
    try:
        assert_same(got, want, "")
    except AssertionError:
        return True
    return False
