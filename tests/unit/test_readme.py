"""The README's first screen stays true and the docs stay findable (issues 22 and 31):
exactly two set-up commands, the first with its venv, the second the test command CI runs;
a README short enough to read in ten minutes that points to docs/index.md; an index that
links every guide in docs/; no link to a file that is not there; and every feature a user
meets after a run named in the docs."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
DOCS = ROOT / "docs"
README = (ROOT / "README.md").read_text(encoding="utf-8")
INDEX = (DOCS / "index.md").read_text(encoding="utf-8")
FIRST_SCREEN = "\n".join(README.splitlines()[:40])
README_MAX_BYTES = 12_000
LINK = re.compile(r"\]\(([^)\s#]+)(?:#[^)]*)?\)")


def _setup_commands() -> list[str]:
    block = re.search(r"```sh\n(.*?)```", FIRST_SCREEN, re.S)
    assert block, "no sh block on the README's first screen"
    return [line for line in block.group(1).splitlines()
            if line.strip() and not line.lstrip().startswith("#")]


def _local_links(text: str) -> set[str]:
    return {link for link in LINK.findall(text) if "://" not in link
            and not link.startswith("mailto:")}


def test_quick_start_is_two_commands_with_a_venv_first() -> None:
    """Regression: the quick start had no venv step and failed on externally-managed Pythons
    (Debian, Ubuntu, Raspberry Pi OS: PEP 668)."""
    first, second = _setup_commands()  # exactly two
    assert first.startswith("python3 -m venv .venv && . .venv/bin/activate && pip install -e .")
    assert "trapflow start" in first and "--duration" in first
    assert second == 'pip install -e ".[test]" && python -m pytest'
    ci = (ROOT / ".ci" / "run").read_text(encoding="utf-8")
    assert second in ci  # CI runs the README's test command itself


def test_the_readme_is_short_and_points_to_the_index() -> None:
    """Regression (issue 31): the README had grown to 55 KB; the detail lives in docs/."""
    size = len(README.encode("utf-8"))
    assert size <= README_MAX_BYTES, f"README.md is {size} bytes: move detail to docs/"
    assert "(docs/index.md)" in README


def test_the_index_links_every_guide() -> None:
    guides = {p.name for p in DOCS.glob("*.md")} - {"index.md"}
    linked = {Path(link).name for link in _local_links(INDEX)
              if (DOCS / link).resolve().parent == DOCS}
    assert sorted(guides - linked) == [], "add these guides to docs/index.md"


@pytest.mark.parametrize(("name", "text", "base"), [
    ("README.md", README, ROOT),
    ("docs/index.md", INDEX, DOCS),
])
def test_every_link_of_the_readme_and_the_index_exists(name: str, text: str,
                                                       base: Path) -> None:
    links = _local_links(text)
    assert links, f"{name} links nothing"
    assert sorted(link for link in links if not (base / link).exists()) == [], name


def test_the_docs_name_what_a_run_leaves_to_use() -> None:
    """Regression: export camtrapdp, report and the COCO output went unmentioned."""
    docs = "\n".join(p.read_text(encoding="utf-8") for p in sorted(DOCS.glob("*.md")))
    for needle in ("trapflow export camtrapdp", "trapflow report", "coco.json"):
        assert needle in docs, needle
