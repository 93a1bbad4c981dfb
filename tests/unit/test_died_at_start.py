"""The error that ends a start-up in which a node died, and its exit status. Regression for
issue 36 item 6: a worker killed while the pipeline started ended the run with exit 2 (a
usage error), 3 tries of 3."""

from __future__ import annotations

import pytest

from trapflow.cli.exit import failed
from trapflow.errors import EXIT_FAILURE, EXIT_USAGE
from trapflow.supervisor.state import died_at_start


@pytest.mark.parametrize(("exitcode", "reason", "status", "line"), [
    # killed by a signal: a runtime failure, whatever it said before
    (-9, "", EXIT_FAILURE, "worker:mono:0 died while the pipeline started: killed by SIGKILL"),
    (-15, "starting", EXIT_FAILURE, "died while the pipeline started: killed by SIGTERM"),
    (-200, "", EXIT_FAILURE, "killed by signal 200"),  # not a signal this system names
    # gone without a word: a runtime failure too
    (3, "", EXIT_FAILURE, "died while the pipeline started: exited with status 3"),
    # gone saying why it cannot start (its plugin, its port): nothing ran as asked
    (1, "cannot start algorithm: no model", EXIT_USAGE,
     "worker:mono:0 cannot start: cannot start algorithm: no model"),
])
def test_a_node_that_died_at_start(exitcode: int, reason: str, status: int, line: str) -> None:
    err = died_at_start("worker:mono:0", exitcode, reason)
    assert line in str(err)
    assert failed(err).exit_code == status
