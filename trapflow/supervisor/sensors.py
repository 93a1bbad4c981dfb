"""The degradation ladder's sensors, read by the supervisor once per ladder interval: CPU
temperature and battery voltage from files (sysfs or any file holding one number), load
average per core, free disk of the run directory, pool backlog and latency from the
broker's stats, outbox backlog from the modem's counters. Owns no sockets.

A sensor that cannot be read is a missing reading (None: it never moves the ladder up),
named once in the log per interval of the rate limiter, not once a second.
"""

from __future__ import annotations

import logging
import os
import shutil
from pathlib import Path

from trapflow.config.ladder import SensorsConfig
from trapflow.runtime.ratelog import RateLimitedLog
from trapflow.supervisor.ladder import Readings
from trapflow.wire.messages import Stats

log = logging.getLogger(__name__)

# A sensor file holds one number; more than this is not a sensor file.
MAX_SENSOR_BYTES = 64
# An unreadable sensor is named again at most this often.
UNREADABLE_LOG_INTERVAL_S = 600.0
_SCALE = {"mC": 1e-3, "C": 1.0, "V": 1.0, "mV": 1e-3, "uV": 1e-6}


class Sensors:
    """Reads one Readings snapshot; the files are opened afresh on every read."""

    def __init__(self, cfg: SensorsConfig, disk_path: Path) -> None:
        self.cfg = cfg
        self.disk_path = disk_path
        self.cores = os.cpu_count() or 1
        self.ratelog = RateLimitedLog(log, UNREADABLE_LOG_INTERVAL_S)

    def read(self, stats: Stats | None = None, outbox_backlog: int | None = None) -> Readings:
        """The sensors now; pool readings from the broker's latest stats."""
        c = self.cfg
        backlog: dict[str, float] = {}
        latency: dict[str, float] = {}
        for name, p in (stats.pools.items() if stats is not None else ()):
            backlog[name] = float(p.pending)
            if p.latency_ms:  # 0: nothing processed yet, no latency to speak of
                latency[name] = p.latency_ms
        return Readings(
            cpu_temp_c=self._file("temperature", c.temperature_path, c.temperature_unit),
            load_per_core=self._load(),
            disk_free_mb=(disk := self._disk())[0],
            disk_free_pct=disk[1],
            outbox_backlog=float(outbox_backlog) if outbox_backlog is not None else None,
            battery_v=self._file("battery", c.battery_path, c.battery_unit),
            pool_backlog=backlog,
            pool_latency_ms=latency,
        )

    def _file(self, what: str, path: str, unit: str) -> float | None:
        if not path:
            return None
        try:
            with open(path, "rb") as f:
                text = f.read(MAX_SENSOR_BYTES + 1)
            if len(text) > MAX_SENSOR_BYTES:
                raise ValueError(f"more than {MAX_SENSOR_BYTES} bytes")
            return float(text.decode("ascii").strip()) * _SCALE[unit]
        except FileNotFoundError:
            # A machine without that sensor (a container, most PCs): said, not warned.
            self.ratelog.log(logging.INFO, what, "ladder: no %s sensor at %s; the reading is "
                             "missing (set ladder.sensors to its file, or \"\")", what, path)
            return None
        except (OSError, ValueError, UnicodeDecodeError) as exc:
            self.ratelog.warning(what, "ladder: cannot read the %s sensor %s (%s); expected one "
                                 "number in %s: the reading is missing", what, path, exc, unit)
            return None

    def _load(self) -> float | None:
        try:
            return os.getloadavg()[0] / self.cores
        except OSError as exc:
            self.ratelog.warning("load", "ladder: no load average (%s)", exc)
            return None

    def _disk(self) -> tuple[float | None, float | None]:
        try:
            du = shutil.disk_usage(self.disk_path)
        except OSError as exc:
            self.ratelog.warning("disk", "ladder: cannot read free disk of %s (%s)",
                                 self.disk_path, exc)
            return None, None
        return du.free / (1 << 20), 100.0 * du.free / du.total if du.total else None
