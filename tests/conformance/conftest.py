"""Conformance harness: third-party data from the real-data kit, read in place, never copied.

The kit lives beside the project (`../shared/realdata` from the project root) or wherever
TRAPFLOW_REALDATA points. Each test that needs it skips with the reason when it is absent
(a user's fresh clone has no kit).
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]


def realdata_root() -> Path:
    """Where the real-data kit is expected: $TRAPFLOW_REALDATA, else ../shared/realdata."""
    env = os.environ.get("TRAPFLOW_REALDATA")
    return Path(env) if env else REPO.parent / "shared" / "realdata"


@pytest.fixture
def realdata() -> Path:
    """The kit's root; skips the test with a clear reason when it is not there."""
    root = realdata_root()
    if not (root / "MANIFEST.md").is_file():
        pytest.skip(f"real-data kit not found at {root} (set TRAPFLOW_REALDATA to its folder)")
    return root


def kit_path(root: Path, *parts: str) -> Path:
    """A file or folder of the kit; skips when that part of the kit is missing."""
    p = root.joinpath(*parts)
    if not p.exists():
        pytest.skip(f"real-data kit has no {Path(*parts)}")
    return p
