"""`trapflow process` on its own cluster serves nothing beyond loopback.

Regression for issue 26 item 10: the local Dask cluster's dashboard (the run's tasks, its
logs, a profiler) was bound to every interface (`dashboard_address=":0"`).
"""

from __future__ import annotations

import ipaddress
from urllib.parse import urlparse

import psutil
import pytest

from trapflow.batch.run import Options, dask_client

pytestmark = pytest.mark.slow  # starts a Dask cluster's worker processes


@pytest.mark.timeout(120)
def test_the_local_cluster_listens_on_loopback_only() -> None:
    pytest.importorskip("distributed")
    me = psutil.Process()
    before = {c.laddr for c in me.net_connections("inet") if c.status == psutil.CONN_LISTEN}
    with dask_client(Options(pools=("mono",), local=1)) as client:
        dashboard = urlparse(str(client.dashboard_link))
        scheduler = urlparse(client.scheduler.address)
        listening = [c.laddr for c in me.net_connections("inet")
                     if c.status == psutil.CONN_LISTEN and c.laddr not in before]
    assert dashboard.hostname == "127.0.0.1", client.dashboard_link
    assert scheduler.hostname == "127.0.0.1", client.scheduler.address
    assert listening, "the scheduler and dashboard listen in this process"
    assert all(ipaddress.ip_address(a.ip).is_loopback for a in listening), listening
