"""Modem configuration and the sender's behaviour without a port."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import msgspec
import pytest

from tests import builders
from tests.conftest import poll_for
from trapflow.config.modem import HealthConfig, ModemConfig, OutboxConfig
from trapflow.modem.codec import LinkCodec
from trapflow.modem.health import HealthMonitor
from trapflow.modem.outbox import Outbox
from trapflow.modem.sender import ModemSender


@pytest.mark.parametrize(
    ("data", "error"),
    [
        ({}, None),
        ({"bit_rate": 0}, "Expected `float` > 0.0 - at `$.bit_rate`"),
        ({"max_frame_payload": 300}, "Expected `int` <= 255 - at `$.max_frame_payload`"),
        ({"ttl_s": {"stereo_vo": -1}}, "Expected `float` >= 0.0"),
        ({"priorities": "scallop"}, "Expected `array`, got `str` - at `$.priorities`"),
        ({"bitrate": 300}, "Object contains unknown field `bitrate`"),
    ],
)
def test_modem_config_table(data: dict[str, Any], error: str | None) -> None:
    if error is None:
        assert msgspec.convert(data, ModemConfig) == ModemConfig()
        return
    with pytest.raises(msgspec.ValidationError) as exc:
        msgspec.convert(data, ModemConfig)
    assert error in str(exc.value)


@pytest.mark.parametrize(
    ("data", "error"),
    [
        ({"fsync_interval_s": 0}, "Expected `float` > 0.0 - at `$.fsync_interval_s`"),
        ({"quota_bytes": 10}, "Expected `int` >= 65536 - at `$.quota_bytes`"),
        ({"path": 3}, "Expected `str`, got `int` - at `$.path`"),
    ],
)
def test_outbox_config_rejects(data: dict[str, Any], error: str) -> None:
    with pytest.raises(msgspec.ValidationError, match=error.replace("$", r"\$")):
        msgspec.convert(data, OutboxConfig)


@pytest.mark.parametrize(
    ("cls", "rank", "ttl", "aggregated"),
    [
        ("new_label", 0, 0.0, False),  # the run's news first, then observations (issue 23)
        ("new_max_n", 1, 0.0, False),
        ("counts", 2, 0.0, False),
        ("track", 3, 0.0, False),
        ("thumb", 4, 0.0, False),  # review thumbnails: before per-pair detections (issue 34)
        ("stereo_ir/scallop", 5, 0.0, False),
        ("mono_ir/crab", 6, 0.0, True),
        ("health", 7, 3600.0, False),
        ("mono_ir/fish", 10, 0.0, True),
        ("stereo_vo", 11, 600.0, True),
        ("whatever", 12, 0.0, False),
    ],
)
def test_class_policy(cls: str, rank: int, ttl: float, aggregated: bool) -> None:
    cfg = ModemConfig()
    assert (cfg.priority_of(cls), cfg.ttl_of(cls), cfg.aggregates(cls)) == (rank, ttl, aggregated)


@pytest.mark.parametrize(
    ("port", "reason"),
    [("", "no port configured"), ("/nonexistent/tty", "cannot open /nonexistent/tty")],
)
def test_sender_inactive_with_reason_while_outbox_fills(
    tmp_path: Path, port: str, reason: str
) -> None:
    path = tmp_path / "outbox.sqlite"
    box = Outbox(path, OutboxConfig())
    sender = ModemSender(path, port, ModemConfig(reopen_interval_s=0.05))
    sender.step()
    for i in range(3):
        box.append({"stereo_ir": {"seq": i, "label": "scallop", "confidence": 0.9}})
    sender.step()
    stats = sender.stats()
    assert stats["state"] == "inactive"
    assert stats["reason"].startswith(reason)
    assert box.counts()[2] == 3
    sender.close()
    box.close()


def test_health_record_fits_the_link(tmp_path: Path) -> None:
    monitor = HealthMonitor(HealthConfig(interval_s=60), tmp_path, lambda: {"mono": (4.5, 10)})
    first = monitor({"backlog": 7, "state": "active"})
    assert first is not None and monitor({"backlog": 7}) is None  # once per interval
    body = first["health"]
    assert (
        body["backlog"] == 7 and body["link"] == "active" and body["pools"] == {"mono": [4.5, 10]}
    )
    assert 0 <= body["mem_pct"] <= 100 and body["disk_free_mb"] > 0
    data = LinkCodec().encode(first)
    assert len(data) <= 48
    assert LinkCodec().decode(data) == first


def test_health_record_says_the_power_model_figures(tmp_path: Path) -> None:
    """With the energy section, the record carries watts at the host's load now and the
    days the battery lasts at that draw (within the board model's range), and still fits."""
    from trapflow.config.schema import EnergyConfig

    monitor = HealthMonitor(HealthConfig(interval_s=60), tmp_path,
                            energy=EnergyConfig(board="pi5", battery_wh=500.0, usable=0.8))
    rec = monitor({"backlog": 0})
    assert rec is not None
    body = rec["health"]
    # Pi 5: 2.7 W idle + 0.4 W for two cameras, at most 4 busy cores at 1.3 W more each.
    assert 3.1 <= body["watts"] <= 8.3
    assert body["days"] == pytest.approx(500.0 * 0.8 / (body["watts"] * 24), abs=0.3)
    data = LinkCodec().encode(rec)
    assert len(data) <= 52 and LinkCodec().decode(data) == rec
    plain = HealthMonitor(HealthConfig(interval_s=60), tmp_path)({"backlog": 0})
    assert plain is not None and "watts" not in plain["health"]


@pytest.mark.parametrize("periodic", [True, False])
def test_a_level_change_sends_a_health_record_at_once(tmp_path: Path, periodic: bool) -> None:
    """The ladder's level (from the broker's stats) changes: a record now, carrying it, even
    inside the interval and with periodic records off; the same level again: none."""
    monitor = HealthMonitor(HealthConfig(enabled=periodic, interval_s=3600), tmp_path)
    first = monitor({"backlog": 0})
    assert (first is not None) == periodic and (first is None or "level" not in first["health"])
    monitor.set_level("full")
    now = monitor({"backlog": 0})
    assert now is not None and now["health"]["level"] == "full"
    monitor.set_level("full")
    assert monitor({"backlog": 0}) is None
    monitor.set_level("ir_slowed")
    rec = monitor({"backlog": 0})
    assert rec is not None and rec["health"]["level"] == "ir_slowed"
    assert LinkCodec().decode(LinkCodec().encode(rec)) == rec
    assert monitor({"backlog": 0}) is None


def test_commands_come_in_and_replies_go_out_first_within_rate_and_budget(tmp_path: Path
                                                                          ) -> None:
    """On a real pty: a COMMAND frame is handed to the node; a queued REPLY leaves before the
    DATA that waits, never before the link is free, and counts in the hourly budget."""
    import os
    import tty

    from trapflow.modem.frame import COMMAND, DATA, REPLY, Deframer, frame

    master, slave = os.openpty()
    tty.setraw(slave)
    os.set_blocking(master, False)
    path = tmp_path / "outbox.sqlite"
    box = Outbox(path, OutboxConfig())
    for i in range(6):
        box.append({"stereo_ir": {"seq": i, "label": "scallop", "confidence": 0.9}})
    cfg = ModemConfig(bit_rate=300, max_frame_payload=32, window=8, aggregate=[], ttl_s={},
                      housekeeping_s=0.01)
    sender = ModemSender(path, os.ttyname(slave), cfg)
    try:
        t = 1000.0
        sender.step(t)  # opens the port, sends the first DATA frame
        os.write(master, frame(COMMAND, b"\x01" * 24))
        poll_for(lambda: sender.step(t + 0.01) is not None and sender.commands, 5,
                 what="the command read")
        assert sender.take_commands() == [b"\x01" * 24]
        sender.send_reply(b"\x02" * 24)
        sender.send_reply(b"\x02" * 24)  # the same reply again (a retransmission): once
        assert sender.step(t + 0.02) > 0 and sender.blocked == "bit rate"
        sender.step(t + 5)
        sender.step(t + 10)
        # A pty hands over what was written in more than one read at times (1 run in 8
        # saw only the first frame): read until three frames came or a second passed.
        deframer, kinds = Deframer(), []
        deadline = time.monotonic() + 1.0
        while len(kinds) < 3 and time.monotonic() < deadline:
            try:
                kinds += [k for k, _ in deframer.feed(os.read(master, 4096))]
            except BlockingIOError:
                time.sleep(0.01)
        assert kinds == [DATA, REPLY, DATA]
        assert sender.stats()["replies"] == 1
        spent = sender.stats()["bytes_last_hour"]
        # A budget already spent holds the reply back.
        sender.cfg.bytes_per_hour = spent
        sender.send_reply(b"\x03" * 24)
        sender.step(t + 20)
        assert sender.blocked == "hourly byte budget spent" and len(sender.replies) == 1
        # A repeat (an answer a replay can ask for) beyond its share is dropped and counted
        # (issue 26): it must not wait for the budget ahead of the answers to new commands.
        sender.replies.clear()
        sender.send_reply(b"\x04" * 24, repeat=True)
        sender.step(t + 30)
        assert sender.stats()["replies_over_share"] == 1 and not sender.replies
    finally:
        sender.close()
        box.close()
        os.close(master)
        os.close(slave)


def test_unsendable_records_are_counted_and_logged_once_per_kind(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """Issue 26 item 5: every VO record was rejected as too large in silence (1,141 of 1,141
    in a power-cut run). A VO line now goes out; a record too large even so is counted
    (`too_large`, in the modem node's counters) and logged once per kind of record."""
    import os
    import tty

    master, slave = os.openpty()
    tty.setraw(slave)
    path = tmp_path / "outbox.sqlite"
    box = Outbox(path, OutboxConfig())
    for _ in range(3):
        box.append(builders.vo_line())
        box.append({"bulky": {"blob": "x" * 400}})
    box.append({"huge": {"blob": "y" * 400}})
    sender = ModemSender(path, os.ttyname(slave), ModemConfig(aggregate=[], ttl_s={}))
    try:
        with caplog.at_level("WARNING", logger="trapflow.modem.sender"):
            sender.step(1000.0)
        told = [r.getMessage() for r in caplog.records if "cannot be sent" in r.getMessage()]
        assert sender.counters["too_large"] == 4
        assert len(told) == 2, told  # one line per kind: bulky, huge
        assert "(bulky)" in told[0] and "too_large" in told[0] and "bytes encoded" in told[0]
        assert sender.stats()["too_large"] == 4
        assert sender.stats()["queued"].get("stereo_vo") or sender.stats()["in_flight"] >= 1
    finally:
        sender.close()
        box.close()
        os.close(master)
        os.close(slave)


MEASURED = {"mono_ir": {"timestamp": "2026-11-29 01:00:00.123", "seq": 1234, "label": "crab",
                        "confidence": 0.84, "box": [750.0, 98.0, 864.0, 166.0],
                        "range_m": 1.337, "range_sd_m": 0.008, "length_m": 0.134,
                        "length_sd_m": 0.008, "xyz": [0.724, 0.171, 1.111],
                        "disparity_px": 98.73, "length_method": "endpoints",
                        "model": "3f9c2a1b", "track": 3, "v": 2}}


def test_an_aggregate_of_measured_detections_carries_its_best_on_the_defaults(
        tmp_path: Path) -> None:
    """Regression (issue 32): one measured mono record made an aggregate 81 bytes where the
    default frame body holds 80, so every aggregate arrived with `"best": []`. The best
    records now ride as their core (what, when, where, which track) when whole ones do not
    fit, the most confident first."""
    import copy
    import os

    master, slave = os.openpty()
    path = tmp_path / "outbox.sqlite"
    box = Outbox(path, OutboxConfig())
    sender = ModemSender(path, os.ttyname(slave), ModemConfig())
    try:
        records = []
        for i, conf in enumerate((0.84, 0.91, 0.55, 0.7)):
            rec = copy.deepcopy(MEASURED)
            rec["mono_ir"].update(seq=1234 + i, confidence=conf)
            records.append(rec)
        summary = sender._summary("mono_ir/*", records)
        best = summary["aggregate"]["best"]
        assert best, summary
        assert [b["mono_ir"]["confidence"] for b in best] == sorted(
            (b["mono_ir"]["confidence"] for b in best), reverse=True)
        assert best[0]["mono_ir"]["confidence"] == 0.91
        assert set(best[0]["mono_ir"]) == {"timestamp", "seq", "label", "confidence", "box",
                                           "track", "v"}
        assert len(sender.codec.encode(summary)) <= ModemConfig().max_frame_payload - 16
        assert sender.codec.decode(sender.codec.encode(summary)) == summary
    finally:
        sender.close()
        box.close()
        os.close(master)
        os.close(slave)
