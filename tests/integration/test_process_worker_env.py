"""The local cluster of `trapflow process` starts its workers without Dask's
MALLOC_TRIM_THRESHOLD_, and with its idle work (profiler, ticks, monitors) less often.

Regression (issue 27, batch that scales): Dask's nanny sets MALLOC_TRIM_THRESHOLD_=65536 in
every worker, and glibc then hands back and faults in again the pages of each image-sized
buffer: a worker spent 17.3 ms of CPU a pair where the plain loop spent 13.2
(benchmarks/process.py, 640x360).
"""

from __future__ import annotations

import os

import pytest

from trapflow.batch.run import LOCAL_QUIET, Options, dask_client

pytestmark = pytest.mark.slow  # starts a Dask cluster's worker processes


def _env() -> dict[str, str | None]:
    return {k: os.environ.get(k) for k in ("MALLOC_TRIM_THRESHOLD_", "OMP_NUM_THREADS")}


def _config() -> dict[str, object]:
    import dask

    return {k: dask.config.get(k) for k in LOCAL_QUIET}


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


@pytest.mark.timeout(120)
def test_local_workers_idle_quietly() -> None:
    """Regression (issue 27): an idle worker burnt 18.5 ms of CPU a second and the client's
    process 22 (the profiler's stack samples every 10 ms, a 20 ms tick, memory polled every
    100 ms), a cost per second that a batch run pays per pair on a busy machine."""
    pytest.importorskip("distributed")
    import dask

    with dask_client(Options(pools=("mono",), local=1)) as client:
        seen = client.run(_config)
        assert dask.config.get("distributed.worker.profile.enabled") is False  # the client's
    assert len(seen) == 1, seen
    for cfg in seen.values():
        assert cfg == {"distributed.worker.profile.enabled": False,
                       "distributed.admin.tick.interval": "200ms",
                       "distributed.worker.memory.monitor-interval": "1s",
                       "distributed.admin.system-monitor.interval": "5s"}, cfg
    # Dask's own defaults are back for anything else this process starts.
    assert dask.config.get("distributed.worker.profile.enabled") is True
