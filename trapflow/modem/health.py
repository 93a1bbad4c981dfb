"""Health telemetry: a small record (uptime, CPU, temperature, memory, disk, backlog, pools,
the degradation ladder's level, the power model's watts and days on the battery, and the
image-health watch's state with its ratios to the baseline).

Sized for the modem link (about 40-65 bytes encoded); sampled with psutil on an interval,
and at once when the ladder's level or the image-health state changes.
"""

from __future__ import annotations

import shutil
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import psutil

from trapflow.config.modem import HealthConfig
from trapflow.config.schema import EnergyConfig
from trapflow.power.energy import BOARDS, estimate
from trapflow.wire.messages import ImageHealth

PoolRates = dict[str, tuple[float, int]]  # pool -> (results per second, drops so far)


def _timestamp(t: float) -> str:
    ms = int(t * 1000) % 1000
    return time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime(t)) + f".{ms:03d}"


def host_uptime_s() -> float:
    """Seconds since the host booted, on a clock no wall-clock step moves (before, the wall
    clock minus the boot time: an NTP fix an hour back made it -775 s, a record the link
    refused)."""
    clock = getattr(time, "CLOCK_BOOTTIME", time.CLOCK_MONOTONIC)
    return time.clock_gettime(clock)


def _temperature() -> float | None:
    try:
        sensors = psutil.sensors_temperatures()
    except (AttributeError, OSError):
        return None
    for name in ("cpu_thermal", "coretemp", "k10temp", "soc_thermal", "thermal_zone0"):
        if sensors.get(name):
            return float(sensors[name][0].current)
    for readings in sensors.values():
        if readings:
            return float(readings[0].current)
    return None


class HealthMonitor:
    """Builds health records; as a callable, returns one per interval (for ModemSender)."""

    def __init__(
        self,
        cfg: HealthConfig | None = None,
        disk_path: str | Path = ".",
        pool_rates: Callable[[], PoolRates] | None = None,
        energy: EnergyConfig | None = None,
        wall: Callable[[], float] = time.time,
        uptime: Callable[[], float] = host_uptime_s,
    ) -> None:
        self.cfg = cfg or HealthConfig()
        self.energy = energy  # with it, the record says watts (and days on the battery)
        self.disk_path = Path(disk_path)
        self.pool_rates = pool_rates
        self.wall = wall  # the record's timestamp: a label
        self.uptime = uptime
        self._next = 0.0
        self.level = ""  # the ladder's level, from the broker's stats ("": none)
        self._level_due = False
        self.image: ImageHealth | None = None  # capture's image-health view, from the stats
        self._image_due = False
        psutil.cpu_percent(None)  # prime: the next call reports usage since now

    def sample(
        self, backlog: int = 0, link: str = "", pools: PoolRates | None = None
    ) -> dict[str, Any]:
        """One health record now."""
        body: dict[str, Any] = {
            "timestamp": _timestamp(self.wall()),
            "uptime_s": max(0, int(self.uptime())),
            "cpu_pct": round(psutil.cpu_percent(None), 1),
            "load1": round(psutil.getloadavg()[0], 2),
        }
        temp = _temperature()
        if temp is not None:
            body["temp_c"] = round(temp, 1)
        body["mem_pct"] = round(psutil.virtual_memory().percent, 1)
        body["disk_free_mb"] = shutil.disk_usage(self.disk_path).free >> 20
        body["backlog"] = backlog
        if link:
            body["link"] = link
        if pools is None and self.pool_rates is not None:
            pools = self.pool_rates()
        if pools:
            body["pools"] = {
                name: [round(rate, 1), int(drops)] for name, (rate, drops) in pools.items()
            }
        if self.level:
            body["level"] = self.level
        if self.image is not None:
            body.update(image_fields(self.image))
        if self.energy is not None:
            body.update(self._power(body["cpu_pct"]))
        return {"health": body}

    def _power(self, cpu_pct: float) -> dict[str, float]:
        """The board's power model at the whole host's CPU load now (on a trap, the trap's
        own work): what ledger.json estimates per role, as one figure the surface can watch."""
        assert self.energy is not None
        cores = (psutil.cpu_count() or 1) * cpu_pct / 100.0
        est = estimate(BOARDS[self.energy.board], {"host": cores}, 1.0,
                       cameras=self.energy.cameras)
        out = {"watts": round(est.watts, 1)}
        if self.energy.battery_wh > 0:
            out["days"] = round(est.days(self.energy.battery_wh, self.energy.usable), 1)
        return out

    def set_level(self, level: str) -> None:
        """The ladder's level as the stats say; a change is reported at once (a record on
        the next call, whatever the interval, even with periodic records off)."""
        if level != self.level:
            self._level_due = bool(level)
            self.level = level

    def set_image(self, image: ImageHealth | None) -> None:
        """The image-health view as the stats say; a change of its state is reported at
        once, as a level change is (fouled, turbid, ok again, the baseline learnt)."""
        if image is None:
            return
        if self.image is not None and image.state != self.image.state:
            self._image_due = True
        self.image = image

    def __call__(self, sender_stats: dict[str, Any]) -> dict[str, Any] | None:
        """A record when the interval has passed, else None."""
        now = time.monotonic()
        due = self._level_due or self._image_due
        if not due and (not self.cfg.enabled or now < self._next):
            return None
        self._level_due = self._image_due = False
        self._next = now + self.cfg.interval_s
        return self.sample(int(sender_stats.get("backlog", 0)), str(sender_stats.get("state", "")))


def image_fields(image: ImageHealth) -> dict[str, Any]:
    """The health record's image fields: the state, and once a baseline is learnt, the
    sharpness, contrast and brightness ratios to it at 0.01 (about 10 bytes on the link)."""
    out: dict[str, Any] = {"image": image.state}
    if image.state != "learning":
        out["image_ratio"] = [round(image.sharpness, 2), round(image.contrast, 2),
                              round(image.brightness, 2)]
    return out
