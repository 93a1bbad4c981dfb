"""The pipeline's TCP port already in use: one line, the policy's exit status, nothing left.

Pins issue 16, item 11: a second pipeline on used ports crashed with a traceback and left
its 60 MB ring segment in /dev/shm.
"""

from __future__ import annotations

import socket
from pathlib import Path

import pytest

from tests.builders import small_source
from tests.conftest import Pipeline, free_base_port, only_pools, write_config
from trapflow.errors import EXIT_USAGE
from trapflow.wire.frame_ring import PREFIX, list_segments

pytestmark = pytest.mark.slow  # starts whole pipelines

SMALL = small_source(10, kind="synthetic")


@pytest.mark.timeout(60)
@pytest.mark.parametrize("transport", ["ipc", "tcp"])
def test_used_remote_port_ends_start_in_one_line_with_nothing_left(
        spawn, run_dir: Path, transport: str) -> None:
    """The one TCP port a pipeline binds is network.remote.bind's (issue 26 item 3 keeps
    every other socket an ipc file, also with the old transport tcp)."""
    base = free_base_port()
    port = base + 1
    cfg = write_config(run_dir.parent / "p.yaml", {
        "source": SMALL, "pools": only_pools({"vo": {"count": 1}}),
        "network": {"transport": transport, "base_port": base,
                    "remote": {"bind": f"tcp://127.0.0.1:{port}"}}})
    with socket.socket() as holder:  # another program (or pipeline) holds the port
        holder.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        holder.bind(("127.0.0.1", port))
        holder.listen(1)
        p: Pipeline = spawn(["--config", str(cfg)], run_dir)
        code, out, err = p.wait(45)
        mine = [n for n in list_segments() if n.startswith(f"{PREFIX}{p.proc.pid}-")]
        kids = p.track()
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert code == EXIT_USAGE, (code, err)
    assert "Traceback" not in err + out
    assert len(lines) == 1, lines
    assert lines[0].startswith("trapflow: error:") and str(port) in lines[0], lines
    assert "in use" in lines[0], lines
    assert mine == [], f"ring segment left behind: {mine}"
    assert kids == [], f"processes left behind: {kids}"
