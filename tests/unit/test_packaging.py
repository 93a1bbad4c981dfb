"""What a non-editable install gets: every package of the tree, under its install name.

Regression: setup.cfg once listed packages by hand and left out trapflow.export, so
`pip install .` (and both Docker images) gave a `trapflow` that died at import. The wheel
itself is built, installed into a fresh venv and run by scripts/check_wheel.sh in CI."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
# Folders of run-time files only, installed as packages of data (setuptools stops
# installing data folders that are not packages).
DATA = {"trapflow.viewer.static", "trapflow_workers.models"}


def _source_packages() -> set[str]:
    """Every folder of trapflow/ and workers/ that holds Python code, by its import name."""
    out: set[str] = set()
    for top, name in (("trapflow", "trapflow"), ("workers", "trapflow_workers")):
        for init in (ROOT / top).rglob("*.py"):
            rel = init.parent.relative_to(ROOT / top)
            if "__pycache__" in rel.parts:
                continue
            out.add(".".join((name, *rel.parts)))
    return out


def test_every_code_folder_is_a_regular_package() -> None:
    """find_packages skips a folder without __init__.py: its modules would not install."""
    missing = sorted(
        str(p.parent.relative_to(ROOT))
        for top in ("trapflow", "workers")
        for p in (ROOT / top).rglob("*.py")
        if "__pycache__" not in p.parts and not (p.parent / "__init__.py").exists()
    )
    assert missing == []


def test_setup_installs_every_package() -> None:
    code = (
        "import sys, setuptools; seen = {}\n"
        "setuptools.setup = lambda **kw: seen.update(kw)\n"
        "sys.argv = ['setup.py']\n"
        "exec(open('setup.py').read())\n"
        "print('\\n'.join(seen['packages']))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, check=True,
                         capture_output=True, text=True, timeout=60).stdout.split()
    assert set(out) - DATA == _source_packages()
    assert set(out) >= DATA
