"""The run ledger without processes: capture counters across restarts, produced never below
what reached the broker, one model for the status line, the ledger and the totals."""

from __future__ import annotations

import json

import pytest

from trapflow.cli.status_text import format_status
from trapflow.supervisor.ledger import Delivered, RunLedger, totals_text
from trapflow.wire.messages import CaptureCounters, PoolStats, Stats


def _stats(pairs_in: int, **pool: int) -> Stats:
    return Stats(t_wall_ns=0, uptime_s=1.0, pairs_in=pairs_in, rate_in=2.0, malformed=0,
                 pools={"vo": PoolStats(**pool)})


@pytest.mark.parametrize("counters", [
    {},
    {"produced": 5, "dropped": 1, "failed": 2, "failed_size": 2, "next_seq": 9},
    {"produced": 1, "source_gave_up": 1, "sync_pairs": 3, "sync_skew_us": 1500},
])
def test_capture_counters_survive_the_wire_form(counters: dict[str, int]) -> None:
    c = CaptureCounters.from_counters(counters)
    again = CaptureCounters.from_counters(c.to_counters())
    assert again == c
    assert c.failed == counters.get("failed", 0)


def test_a_restarted_capture_goes_on_counting_and_numbering() -> None:
    led = RunLedger()
    led.on_capture(CaptureCounters(produced=40, dropped=2, failures={"size": 1}, next_seq=40))
    assert led.retire_capture(margin=110) == 150  # past anything sent after its last beat
    led.on_capture(CaptureCounters(produced=7, failures={"size": 2, "truncated": 1},
                                   next_seq=157))
    c = led.capture()
    assert (c.produced, c.dropped, c.failures) == (47, 2, {"size": 3, "truncated": 1})
    assert led.capture_counts() == {"dropped": 2, "failed": 4, "failed_size": 3,
                                    "failed_truncated": 1, "produced": 47,
                                    "source_errors": 0}


def test_produced_is_never_below_what_reached_the_broker() -> None:
    """Regression (issue 16, item 4): a killed capture had not reported its last pairs, so
    "produced" undercounted what the pools received (2,191 produced, 2,212 results)."""
    led = RunLedger()
    led.on_capture(CaptureCounters(produced=90))
    led.on_stats(_stats(100, received=100, processed=100))
    ledger = led.ledger({"vo": "ordered"}, {"vo": 0})
    assert ledger["produced"] == 100
    assert ledger["pools"]["vo"]["lost"] == 0


def test_a_dead_broker_keeps_its_counts_in_status_and_ledger() -> None:
    led = RunLedger()
    led.on_capture(CaptureCounters(produced=130))
    led.on_stats(_stats(100, received=100, processed=95, pending=3, in_flight=2, workers=1))
    led.retire_broker()
    led.on_stats(_stats(30, received=30, processed=30, workers=1, rate=2))
    ledger = led.ledger({"vo": "ordered"}, {"vo": 3},
                        {"gave_up": 1, "retries": 1, "capped": 0, "timeline": []})
    vo = ledger["pools"]["vo"]
    assert (vo["processed"], vo["lost"], vo["restarts"]) == (125, 5, 3)
    assert ledger["reached_broker"] == 130
    line = led.status_text(12.0, {"vo": 3})
    assert "in   2.0/s (130)" in line and "vo 1w" in line and "rst 3" in line
    text = totals_text(ledger)
    assert "130 pairs captured" in text and "processed 125" in text and "restarts 3" in text
    assert "1 give-ups, 1 retries" in text


def test_no_stats_yet() -> None:
    assert RunLedger().status_text(1.0, {}) == "   1.0s | waiting for stats"
    assert RunLedger().ledger({}, {})["pools"] == {}


def _line(kind: str, seq: int, **extra: object) -> bytes:
    return json.dumps({kind: {"timestamp": "t", "seq": seq, **extra}}).encode() + b"\n"


@pytest.mark.parametrize(("lines", "counts", "unreadable"), [
    ([_line("mono_ir", 1), _line("mono_ir", 2)], {"mono_ir": 2}, 0),
    # one result, three detections: three lines, one pair
    ([_line("mono_ir", 1, label="crab")] * 3, {"mono_ir": 1}, 0),
    # resent to a restarted normalizer before it acknowledged: written twice, counted once
    ([_line("stereo_vo", 5), _line("stereo_vo", 6), _line("stereo_vo", 5)], {"stereo_vo": 2}, 0),
    ([_line("tags", 3), _line("stereo_vo", 3)], {"tags": 1, "stereo_vo": 1}, 0),
    ([b'{"mono_ir":{"seq":4,"lab\n', _line("mono_ir", 5)], {"mono_ir": 1}, 1),  # torn write
])
def test_delivered_counts_distinct_results_per_kind(lines: list[bytes], counts: dict[str, int],
                                                    unreadable: int) -> None:
    """Lines that name no pool (a normalizer from before lines did): counted per kind."""
    whole = Delivered()
    whole.feed(b"".join(lines))
    assert (whole.kinds, whole.pools, whole.unreadable) == (counts, {}, unreadable)
    # Fed in pieces that cut lines anywhere (the file read while the normalizer writes).
    data = b"".join(lines)
    pieces = Delivered()
    for i in range(0, len(data), 7):
        pieces.feed(data[i:i + 7])
    assert (pieces.kinds, pieces.unreadable, pieces.offset) == (counts, unreadable, len(data))


def test_delivered_waits_for_the_end_of_a_line() -> None:
    d = Delivered()
    d.feed(_line("mono_ir", 1)[:-5])
    assert d.kinds == {} and d.offset == 0
    d.feed(_line("mono_ir", 1)[-5:])
    assert d.kinds == {"mono_ir": 1}


def test_two_pools_of_one_plugin_are_each_credited_their_own_lines() -> None:
    """Regression (issue 32): the routes kept kind -> pool, so with two pools of one plugin
    (a local and a remote digest pool) every line of that kind was credited to the last pool
    routed: the other got no kind and its processed was the broker's, and the credited pool
    counted both pools' lines. A line names its pool: each is credited its own, and a seq
    both pools processed counts once for each."""
    led = RunLedger()
    led.on_capture(CaptureCounters(produced=10))
    led.on_stats(Stats(t_wall_ns=0, uptime_s=1.0, pairs_in=10, rate_in=2.0, malformed=0,
                       pools={"hash": PoolStats(received=10, processed=10),
                              "hash_remote": PoolStats(received=10, processed=4, lost=6)}))
    led.on_normalizer({"route:hash:digest": 1, "route:hash_remote:digest": 1})
    led.delivered.feed(b"".join([*(_line("digest", s, pool="hash") for s in range(10)),
                                 *(_line("digest", s, pool="hash_remote") for s in range(4)),
                                 _line("digest", 2, pool="hash")]))  # written twice
    pools = led.ledger({"hash": "latest", "hash_remote": "latest"}, {})["pools"]
    assert (pools["hash"]["processed"], pools["hash_remote"]["processed"]) == (10, 4)
    assert pools["hash"]["kinds"] == pools["hash_remote"]["kinds"] == ["digest"]
    assert pools["hash_remote"]["lost"] == 6 and led.delivered.total() == 14


def test_lines_naming_no_pool_are_credited_by_kind_to_its_one_pool() -> None:
    """The fallback for a normalizer from before lines named their pool: a kind one pool
    alone makes is that pool's; a kind two pools make is neither's (its pools keep the
    broker's count, as before lines were counted)."""
    d = Delivered()
    d.feed(b"".join([_line("stereo_vo", 1), _line("stereo_vo", 2), _line("digest", 1),
                     _line("mono_ir", 1, pool="mono")]))
    routes = {"vo": {"stereo_vo"}, "a": {"digest"}, "b": {"digest"}, "mono": {"mono_ir"}}
    assert d.by_pool(routes) == {"vo": 2, "a": 0, "b": 0, "mono": 1}
    assert d.by_pool({}) == {"mono": 1}


def test_processed_is_what_was_delivered_once_routed() -> None:
    """Regression (issue 16, item 4): after a broker kill the ledger counted as lost pairs
    whose results were written (its last stats were up to a second old)."""
    led = RunLedger()
    led.on_capture(CaptureCounters(produced=100))
    led.on_stats(_stats(100, received=100, processed=80, pending=5, in_flight=5, lost=10))
    assert led.ledger({"vo": "ordered"}, {})["pools"]["vo"]["processed"] == 80  # not routed
    led.on_normalizer({"lines": 97, "route:vo:stereo_vo": 1})
    led.delivered.feed(b"".join(_line("stereo_vo", s, pool="vo") for s in range(97)))
    vo = led.ledger({"vo": "ordered"}, {})["pools"]["vo"]
    assert (vo["processed"], vo["lost"]) == (97, 3)


def test_produced_covers_what_one_pool_accounts_for() -> None:
    """Regression (issue 16, item 4): a capture and a broker killed before reporting their
    last pairs; the pool's written results show those pairs existed."""
    led = RunLedger()
    led.on_capture(CaptureCounters(produced=50))
    led.on_stats(_stats(55, received=55, processed=50, dropped=2, workers=1))
    led.on_normalizer({"route:vo:stereo_vo": 1})
    led.delivered.feed(b"".join(_line("stereo_vo", s) for s in range(58)))
    ledger = led.ledger({"vo": "ordered"}, {})
    assert ledger["produced"] == 60 and ledger["pools"]["vo"]["lost"] == 0


def test_status_shows_in_progress_pairs_as_not_lost_until_the_end() -> None:
    led = RunLedger()
    led.on_capture(CaptureCounters(produced=20))
    led.on_stats(_stats(20, received=20, processed=17, pending=1, in_flight=2, workers=1))
    live = led.ledger({"vo": "ordered"}, {}, final=False)["pools"]["vo"]
    assert (live["lost"], live["in_progress"]) == (0, 3)
    assert "lost 0, in progress 3," in totals_text(led.ledger({"vo": "ordered"}, {},
                                                              final=False))
    end = led.ledger({"vo": "ordered"}, {})["pools"]["vo"]
    assert end["lost"] == 3 and "in_progress" not in end


def test_trapflow_status_renders_the_supervision_timeline_and_the_ledger() -> None:
    led = RunLedger()
    led.on_capture(CaptureCounters(produced=20))
    led.on_stats(_stats(20, received=20, processed=20, workers=1))
    timeline = [{"t_s": 12.5, "node": "worker:vo:0", "kind": "gave_up",
                 "reason": "gave up after 5 restarts in 60 s (last exit status -9)"},
                {"t_s": 72.5, "node": "worker:vo:0", "kind": "retry",
                 "reason": "retrying after a cool-down of 60 s (give-up 1)"}]
    sup = {"gave_up": 1, "retries": 1, "capped": 0, "timeline": timeline}
    reply = {"run_dir": "runs/x", "uptime_s": 80.0, "nodes": [], "stats": None,
             "supervision": sup, "ledger": led.ledger({"vo": "ordered"}, {"vo": 6}, sup,
                                                      final=False)}
    text = format_status(reply)
    assert "supervision: 1 give-ups, 1 retries, 0 capped restarts" in text
    assert "worker:vo:0" in text and "retry" in text and "gave_up" in text
    assert "vo: processed 20" in text and "restarts 6" in text


def test_status_says_the_energy_estimate() -> None:
    """`trapflow status` ends with the energy line of ledger.json's estimate so far."""
    from trapflow.config.schema import EnergyConfig
    from trapflow.supervisor.report import energy_section

    led = RunLedger()
    ledger = led.ledger({}, {}, final=False)
    ledger["energy"] = energy_section(EnergyConfig(), {"mono": 360.0}, 3600.0, (20, 80))
    text = format_status({"run_dir": "runs/x", "uptime_s": 3600.0, "nodes": [],
                          "stats": None, "ledger": ledger})
    assert text.endswith("energy (pi5 model): 0.1 cores busy, 3.23 W, 77.5 Wh/day; "
                         "motion gate active 20 s (20 %), idle 80 s")


def _live_and_final(produced: int, pairs_in: int, written: int | None,
                    **pool: int) -> tuple[dict[str, int], dict[str, int]]:
    """The vo pool's row of the live ledger and of the final one after a failure."""
    led = RunLedger()
    led.on_capture(CaptureCounters(produced=produced))
    led.on_stats(_stats(pairs_in, received=pairs_in, workers=1, **pool))
    if written is not None:  # results.jsonl holds `written` results of the pool
        led.on_normalizer({"route:vo:stereo_vo": 1})
        led.delivered.feed(b"".join(_line("stereo_vo", s) for s in range(written)))
    live = led.ledger({"vo": "ordered"}, {}, final=False)["pools"]["vo"]
    end = led.ledger({"vo": "ordered"}, {})["pools"]["vo"]
    return live, end


@pytest.mark.parametrize(
    ("produced", "pairs_in", "written", "pool", "live_lost", "in_progress", "final_lost"), [
        # captured, not yet at the broker: on the capture link
        (25, 20, None, {"processed": 17, "pending": 1, "in_flight": 2}, 0, 8, 8),
        # answered by the worker, not yet written: on its way to results.jsonl
        (20, 20, 15, {"processed": 20}, 0, 5, 5),
        # both at once, with a queue and a worker busy
        (30, 26, 18, {"processed": 22, "pending": 2, "in_flight": 2}, 0, 12, 12),
        # a healthy run with nothing on its way
        (20, 20, 20, {"processed": 20}, 0, 0, 0),
        # what a broker counted lost (a worker evicted with its pair) is lost at once
        (20, 20, None, {"processed": 15, "lost": 3, "pending": 2}, 3, 2, 5),
        # the broker's count never exceeds what is not in a state
        (20, 20, 19, {"processed": 20, "lost": 4}, 1, 0, 1),
    ])
def test_live_ledger_counts_pairs_on_their_way_as_in_progress_not_lost(
        produced: int, pairs_in: int, written: int | None, pool: dict[str, int],
        live_lost: int, in_progress: int, final_lost: int) -> None:
    """Regression (issue 22, item 1): the live ledger (viewer, `trapflow status` totals)
    counted pairs captured but not yet at the broker, and answered but not yet written, as
    lost ("lost 1" to "lost 10" per pool on healthy runs whose ledger.json said 0)."""
    live, end = _live_and_final(produced, pairs_in, written, **pool)
    assert (live["lost"], live["in_progress"]) == (live_lost, in_progress)
    assert (end["lost"], "in_progress" in end) == (final_lost, False)


def test_a_retired_broker_s_held_pairs_are_lost_in_the_live_ledger() -> None:
    """What a dead broker held can never finish: lost while the run goes on, not in progress
    (kept by the fix of issue 22, item 1)."""
    led = RunLedger()
    led.on_capture(CaptureCounters(produced=40))
    led.on_stats(_stats(30, received=30, processed=25, pending=3, in_flight=2, workers=1))
    led.retire_broker()
    led.on_stats(_stats(10, received=10, processed=8, pending=1, in_flight=1, workers=1))
    live = led.ledger({"vo": "ordered"}, {}, final=False)["pools"]["vo"]
    assert (live["processed"], live["lost"], live["in_progress"]) == (33, 5, 2)
    text = totals_text(led.ledger({"vo": "ordered"}, {}, final=False))
    assert "lost 5, in progress 2," in text


@pytest.mark.parametrize(("final", "kept", "gated", "lost", "in_progress"), [
    (False, 2, 30, 0, 7),  # live: the kept pre-roll is in progress with pending and in flight
    (True, 0, 32, 5, None),  # ended after a failure: the broker's finish gated what it kept
])
def test_gated_pairs_are_their_own_state(final: bool, kept: int, gated: int, lost: int,
                                         in_progress: int | None) -> None:
    """Pairs the motion gate withheld are counted gated, never dropped or lost: received =
    processed + gated + pending + in flight + kept while the run goes on."""
    led = RunLedger()
    led.on_capture(CaptureCounters(produced=100))
    led.on_stats(_stats(100, received=100, processed=63, gated=gated, kept=kept, pending=3,
                        in_flight=2))
    pool = led.ledger({"vo": "fifo:8"}, {}, final=final)["pools"]["vo"]
    assert (pool["gated"], pool["dropped_by_policy"], pool["lost"]) == (gated, 0, lost)
    assert pool.get("in_progress") == in_progress
    assert "gated" in totals_text(led.ledger({"vo": "fifo:8"}, {}))


def test_a_dead_brokers_kept_pre_roll_counts_gated_not_lost() -> None:
    led = RunLedger()
    led.on_capture(CaptureCounters(produced=50))
    led.on_stats(_stats(50, received=50, processed=20, gated=25, kept=3, in_flight=2))
    led.retire_broker()
    led.on_stats(_stats(0))
    pool = led.ledger({"vo": "fifo:8"}, {})["pools"]["vo"]
    assert (pool["processed"], pool["gated"], pool["lost"]) == (20, 28, 2)
