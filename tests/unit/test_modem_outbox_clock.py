"""The outbox's clock: time-to-live, retention and the hourly budget are measured on a clock
no wall-clock step moves, and which goes on across a reboot. Regression: the wall clock
stepped a day forward expired every VO record waiting for the link at once, unsent."""

from __future__ import annotations

import os
import time
import tty
from pathlib import Path

import pytest

from tests import builders
from trapflow.config.modem import ModemConfig, OutboxConfig
from trapflow.modem import outbox as outbox_mod
from trapflow.modem.outbox import Outbox, OutboxQueue
from trapflow.modem.sender import ModemSender

DAY_NS = 86_400 * 10**9


def test_a_day_step_forward_expires_nothing(tmp_path: Path,
                                            monkeypatch: pytest.MonkeyPatch) -> None:
    master, slave = os.openpty()
    tty.setraw(slave)
    path = tmp_path / "outbox.sqlite"
    box = Outbox(path, OutboxConfig())
    for _ in range(20):
        box.append(builders.vo_line())
    cfg = ModemConfig(aggregate=[], ttl_s={"stereo_vo": 600.0}, bit_rate=1)
    sender = ModemSender(path, os.ttyname(slave), cfg)
    real_ns = time.time_ns
    monkeypatch.setattr(time, "time_ns", lambda: real_ns() + DAY_NS)
    monkeypatch.setattr(time, "time", lambda: real_ns() / 1e9 + 86_400)
    try:
        sender.step(time.monotonic())
        assert sender.counters["expired"] == 0
        assert OutboxQueue(path, OutboxConfig()).states().get("expired", 0) == 0
        # Ten minutes later on the monotonic clock they do expire (those not in flight).
        mono_ns = time.monotonic_ns
        monkeypatch.setattr(time, "monotonic_ns", lambda: mono_ns() + 601 * 10**9)
        sender.step(time.monotonic() + 601)
        assert sender.counters["expired"] > 0
    finally:
        sender.close()
        box.close()
        os.close(master)
        os.close(slave)


def test_the_clock_goes_on_from_the_newest_time_after_a_reboot(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "outbox.sqlite"
    box = Outbox(path)
    box.append(builders.vo_line())
    box.close()
    queue = OutboxQueue(path, OutboxConfig())
    (stored,) = queue.read()
    assert abs(stored.up_ns - queue.clock_ns()) < 10 * 10**9  # same boot: the same clock
    queue.close()
    # A power cut: a new boot, whose monotonic clock starts again near 0.
    monkeypatch.setattr(outbox_mod, "_boot_id", lambda: b"another-boot")
    monkeypatch.setattr(time, "monotonic_ns", lambda: 5 * 10**9)
    queue = OutboxQueue(path, OutboxConfig())
    assert queue.clock_ns() >= stored.up_ns  # time never goes back, the time off is not counted
    assert queue.expire("stereo_vo", queue.clock_ns() - 60 * 10**9) == 0
    queue.close()
