"""What the README promises of the command line, with real processes: `trapflow process`
fails in one line on stderr, `trapflow start --view` prints the page's address."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.conftest import Pipeline, run_process
from tests.integration.viewer_util import free_port


@pytest.mark.timeout(150)
def test_process_error_is_one_line_without_dask_tracebacks(tmp_path: Path) -> None:
    """Regression (issue 22, item 8): an input that cannot be read gave 23 lines on stderr,
    3 of them Dask's tracebacks of the same error (one per retry)."""
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(bytes(range(256)) * 20)
    code, out, err = run_process([str(junk), "--workers", "mono", "--out",
                                  str(tmp_path / "out"), "--local", "1"])
    assert code == 1, err
    errors = [line for line in err.splitlines() if "error" in line.lower()]
    assert len(errors) == 1 and errors[0].startswith("trapflow: error: "), err
    assert "cannot read" in errors[0] and "ledger.json" in errors[0], err
    assert "Traceback" not in err and "distributed." not in err, err
    assert "junk.mcap" in out  # the summary table still names the input


@pytest.mark.slow  # starts a whole pipeline
@pytest.mark.timeout(120)
def test_start_view_prints_the_page_address(spawn, run_dir: Path) -> None:
    """Regression (issue 22, item 8): `trapflow start --view PORT` served the page but never
    said where; the address was only in trapflow.log."""
    port = free_port()
    p: Pipeline = spawn(["--workers", "vo=1", "--size", "160x120", "--duration", "3",
                         "--view", str(port)], run_dir)
    code, out, err = p.wait(90)
    assert code == 0, err
    url = f"http://127.0.0.1:{port}/"
    shown = [line for line in out.splitlines() if line.startswith("viewer: ")]
    assert shown == [f"viewer: {url}"], out
    assert out.index("starting") < out.index("viewer: ")  # printed while it starts

