"""The local cluster of `trapflow process` starts its workers without Dask's
MALLOC_TRIM_THRESHOLD_.

Regression (issue 27, batch that scales): Dask's nanny sets MALLOC_TRIM_THRESHOLD_=65536 in
every worker, and glibc then hands back and faults in again the pages of each image-sized
buffer: a worker spent 17.3 ms of CPU a pair where the plain loop spent 13.2
(scripts/bench_process.py, 640x360).
"""

from __future__ import annotations

import os

import pytest

from trapflow.batch.run import Options, dask_client

pytestmark = pytest.mark.slow  # starts a Dask cluster's worker processes


def _env() -> dict[str, str | None]:
    return {k: os.environ.get(k) for k in ("MALLOC_TRIM_THRESHOLD_", "OMP_NUM_THREADS")}


@pytest.mark.timeout(120)
def test_local_workers_run_without_the_malloc_trim_threshold(
        monkeypatch: pytest.MonkeyPatch) -> None:
    pytest.importorskip("distributed")
    import dask

    # As `trapflow process` starts: a fresh process, the variable unset. (Any LocalCluster
    # started earlier in this process with Dask's defaults wrote it into os.environ, and
    # workers inherit the parent's environment.)
    monkeypatch.delenv("MALLOC_TRIM_THRESHOLD_", raising=False)

    before = dask.config.get("distributed.nanny.pre-spawn-environ")
    with dask_client(Options(pools=("mono",), local=2)) as client:
        envs = client.run(_env)
    assert len(envs) == 2, envs
    for env in envs.values():
        assert env["MALLOC_TRIM_THRESHOLD_"] is None, env
        assert env["OMP_NUM_THREADS"] == "1", env  # the rest of Dask's environment stays
    # The change is the cluster's own: Dask's configuration is as it was.
    assert dask.config.get("distributed.nanny.pre-spawn-environ") == before
    assert before.get("MALLOC_TRIM_THRESHOLD_") == 65536
