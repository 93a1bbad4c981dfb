"""A process that ran the AprilTag C library exits cleanly (real child processes, so not
among the unit tests)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow  # renders 1280x720 frames in two fresh interpreters


@pytest.mark.timeout(120)
def test_a_process_that_used_the_c_library_exits_cleanly() -> None:
    """Regression: pupil-apriltags frees its tag families before the detector that still reads
    them; a process whose detector had run on the synthetic world's 1280x720 frames crashed at
    exit (SIGSEGV or a glibc abort) in 4 of 6 runs like these before detectors were kept."""
    pytest.importorskip("pupil_apriltags")
    code = (
        "from trapflow.synth.options import SynthOptions\n"
        "from trapflow.synth.render import World\n"
        "from trapflow_workers.apriltags import AprilTags\n"
        "from trapflow.testing.kit import make_context, make_pair\n"
        "from trapflow.calibration.camera import StereoRig\n"
        "RIG = StereoRig.from_fov(1280, 720, 70.0, 0.12)\n"
        "world = World(RIG, seed=2, moving=True, rate_hz=15.0,\n"
        "              options=SynthOptions(tags=8, tag_size_m=0.12))\n"
        "w = AprilTags()\n"
        "w.configure({'detector': 'apriltag', 'tag_size_m': 0.12}, make_context(RIG))\n"
        "found = 0\n"
        "for i in (0, 6, 12):\n"
        "    left, right, _ = world.render(i)\n"
        "    found += len(w.process(make_pair(left, right)).tags)\n"
        "assert found > 0\n"
    )
    for _ in range(2):
        done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                              cwd=Path(__file__).resolve().parents[2], timeout=100)  # fmt: skip
        assert done.returncode == 0, done.stderr[-2000:]
