"""The README's first screen and feature list stay true (issue 22, item 8): exactly two set-up
commands, the first with its venv, the second the test command CI runs; every feature a user
meets after a run is named, and every doc it links exists."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
README = (ROOT / "README.md").read_text(encoding="utf-8")
FIRST_SCREEN = "\n".join(README.splitlines()[:40])


def _setup_commands() -> list[str]:
    block = re.search(r"```sh\n(.*?)```", FIRST_SCREEN, re.S)
    assert block, "no sh block on the README's first screen"
    return [line for line in block.group(1).splitlines()
            if line.strip() and not line.lstrip().startswith("#")]


def test_quick_start_is_two_commands_with_a_venv_first() -> None:
    """Regression: the quick start had no venv step and failed on externally-managed Pythons
    (Debian, Ubuntu, Raspberry Pi OS: PEP 668)."""
    first, second = _setup_commands()  # exactly two
    assert first.startswith("python3 -m venv .venv && . .venv/bin/activate && pip install -e .")
    assert "trapflow start" in first and "--duration" in first
    assert second == 'pip install -e ".[test]" && python -m pytest'
    ci = (ROOT / ".ci" / "run").read_text(encoding="utf-8")
    assert second in ci  # CI runs the README's test command itself


def test_readme_names_what_a_run_leaves_to_use() -> None:
    """Regression: export camtrapdp, report, the COCO output and two docs went unmentioned."""
    for needle in ("trapflow export camtrapdp", "trapflow report", "coco.json",
                   "docs/exports.md", "docs/recordings.md"):
        assert needle in README, needle


def test_every_linked_doc_exists() -> None:
    links = set(re.findall(r"\]\((docs/[^)#]+)", README))
    assert links, "the README links no doc"
    assert sorted(link for link in links if not (ROOT / link).exists()) == []
