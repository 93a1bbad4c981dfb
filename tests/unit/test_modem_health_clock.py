"""Health's uptime under a stepped wall clock. Regression: uptime was the wall clock minus
the boot time; an NTP fix an hour back after a boot without a real-time clock made it
negative (-775 s), and such records were refused by the link's encoder."""

from __future__ import annotations

import time
from pathlib import Path

import pytest

from trapflow.config.modem import HealthConfig
from trapflow.modem.codec import LinkCodec
from trapflow.modem.health import HealthMonitor, host_uptime_s


def test_uptime_ignores_a_wall_clock_step_back(tmp_path: Path,
                                                monkeypatch: pytest.MonkeyPatch) -> None:
    real = time.time
    up = host_uptime_s()
    monkeypatch.setattr(time, "time", lambda: real() - up - 3600.0)  # before the boot
    record = HealthMonitor(HealthConfig(interval_s=60), tmp_path).sample()
    assert record["health"]["uptime_s"] == pytest.approx(up, abs=5)
    assert LinkCodec().decode(LinkCodec().encode(record))["health"]["uptime_s"] >= 0


def test_the_timestamp_is_the_wall_clock_label(tmp_path: Path) -> None:
    monitor = HealthMonitor(HealthConfig(), tmp_path, wall=lambda: 86_400.5, uptime=lambda: 42.7)
    body = monitor.sample()["health"]
    assert body["timestamp"] == "1970-01-02 00:00:00.500" and body["uptime_s"] == 42
