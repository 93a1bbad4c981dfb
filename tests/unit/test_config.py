"""Config tables: every shipped file validates, bad input names its key, CLI counts parse."""

from __future__ import annotations

from pathlib import Path

import msgspec
import pytest

from trapflow.config import schema as config
from trapflow.config.schema import Policy, SourceConfig, parse_policy
from trapflow.errors import ConfigError

CONFIGS = sorted((Path(__file__).resolve().parents[2] / "configs").glob("*.yaml"))


def test_configs_exist() -> None:
    assert any(p.name == "default.yaml" for p in CONFIGS)


@pytest.mark.parametrize("path", CONFIGS, ids=lambda p: p.name)
def test_every_shipped_config_validates(path: Path) -> None:
    config.load(path)


def test_default_yaml_documents_the_defaults() -> None:
    """configs/default.yaml must equal the built-in defaults, key for key."""
    shipped = config.load(next(p for p in CONFIGS if p.name == "default.yaml"))
    assert msgspec.to_builtins(shipped) == msgspec.to_builtins(config.Config())


@pytest.mark.parametrize(
    ("data", "error"),
    [
        ({"bogus": 1}, "unknown field `bogus`"),
        ({"source": {"rate_hz": 0}}, r"\$.source.rate_hz"),
        ({"source": {"width": 8}}, r">= 16 - at `\$.source.width`"),
        ({"source": {"jpeg_quality": 101}}, r"\$.source.jpeg_quality"),
        ({"source": {"encoding": "png"}}, r"\$.source.encoding"),
        ({"source": {"seed": "abc"}}, r"Expected `int`, got `str` - at `\$.source.seed`"),
        ({"pools": {"mono": {"count": -1}}}, r"\$.pools.mono.count"),
        ({"pools": {"mono": {"policy": "newest"}}}, r"expected latest.*\$.pools.mono"),
        ({"pools": {"mono": {"policy": "fifo:0"}}}, "got 'fifo:0'"),
        ({"pools": {"mono": {"nice": 40}}}, r"\$.pools.mono.nice"),
        ({"pools": {"mono": {"affinity": [-1]}}}, r"\$.pools.mono.affinity"),
        ({"pools": {"mono": {"colour": "red"}}}, r"unknown field `colour` - at `\$.pools.mono`"),
        ({"pools": {"vo": {"count": 2, "policy": "ordered"}}}, "ordered policy takes count 0 or 1"),
        ({"pools": {"bad-name": {}}}, "must be an identifier"),
        # A gated ordered pool would see every withheld pair as a gap: refused, with why.
        ({"pools": {"vo": {"gate": "motion"}}},
         r"an ordered pool \(visual odometry\) needs every pair.*\$.pools.vo"),
        ({"pools": {"mono": {"gate": "sometimes"}}}, r"\$.pools.mono.gate"),
        ({"gate": {"pre_roll": 101}}, r"\$.gate.pre_roll"),
        ({"gate": {"keepalive_s": 0}}, r"\$.gate.keepalive_s"),
        ({"normalizer": {"flush_interval_s": 5}}, r"\$.normalizer.flush_interval_s"),
        ({"network": {"host": "0.0.0.0"}}, "expected a loopback host"),
        ({"network": {"transport": "udp"}}, r"\$.network.transport"),
        ({"log_level": "LOUD"}, r"\$.log_level"),
        ({"log_file": {"max_bytes": 100}}, r">= 65536 - at `\$.log_file.max_bytes`"),
        ({"log_file": {"backups": 0}}, r"\$.log_file.backups"),
        ([1, 2], "Expected `object`"),
    ],
)
def test_bad_config_names_the_key(data: object, error: str) -> None:
    with pytest.raises(ConfigError, match=error):
        config.from_data(data, "test.yaml")


def test_load_reports_file_problems(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="cannot read config"):
        config.load(tmp_path / "missing.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("pools: [unclosed")
    with pytest.raises(ConfigError, match="not valid YAML"):
        config.load(bad)


@pytest.mark.parametrize(
    ("text", "expected", "error"),
    [
        ("mono=2,stereo=1,vo=1", {"mono": 2, "stereo": 1, "vo": 1}, None),
        (" mono=1 ", {"mono": 1}, None),
        ("mono=x", None, "expected NAME=COUNT.*got 'mono=x'"),
        ("mono=0", {"mono": 0}, None),  # a remote pool with no local worker (with_workers)
        ("mono=-1", None, "0 or more, got 'mono=-1'"),
        ("mono", None, "got 'mono'"),
        ("=3", None, "got '=3'"),
        ("mono=1,,vo=1", None, "got ''"),
        ("", None, "empty string"),
        ("mono=1,mono=2", None, "given twice"),
    ],
)
def test_parse_workers(text: str, expected: dict[str, int] | None, error: str | None) -> None:
    if error is None:
        assert config.parse_workers(text) == expected
    else:
        with pytest.raises(ConfigError, match=error):
            config.parse_workers(text)


def test_with_workers_switches_off_unnamed_pools_and_adds_known_plugins() -> None:
    cfg = config.with_workers(config.Config(), {"mono": 2, "noop": 1}, ["mono", "noop"])
    assert cfg.pools["mono"].count == 2
    assert cfg.pools["stereo"].count == 0
    assert cfg.pools["noop"].count == 1


@pytest.mark.parametrize(("remote", "error"), [
    (True, None),                      # the README's Jetson case: every worker is remote
    (False, "pools.mono.remote: true"),  # nobody would ever process its pairs: said why
])
def test_with_workers_takes_0_for_a_remote_pool(remote: bool, error: str | None) -> None:
    """Regression (issue 22, item 8): `--workers mono=0` was refused although the README
    says a remote pool may run no local worker."""
    cfg = config.from_data({"pools": {"mono": {"remote": remote}},
                            "network": {"remote": {"bind": "tcp://127.0.0.1:5560"}}})
    if error is None:
        assert config.with_workers(cfg, {"mono": 0, "vo": 1}, ["mono", "vo"]).pools[
            "mono"].count == 0
    else:
        with pytest.raises(ConfigError, match=error):
            config.with_workers(cfg, {"mono": 0, "vo": 1}, ["mono", "vo"])


def test_with_workers_rejects_unknown_algorithm() -> None:
    with pytest.raises(ConfigError, match="unknown algorithm 'sonar'"):
        config.with_workers(config.Config(), {"sonar": 1}, ["mono"])


@pytest.mark.parametrize(
    ("text", "policy"),
    [("latest", Policy("latest", 1)), ("fifo:4", Policy("fifo", 4)),
     ("ordered", Policy("ordered", 16)), ("ordered:3", Policy("ordered", 3))],
)
def test_parse_policy(text: str, policy: Policy) -> None:
    assert parse_policy(text) == policy
    assert parse_policy(str(policy)) == policy


@pytest.mark.parametrize("text", ["", "fifo", "fifo:", "fifo:-1", "latest:2", "lifo:3"])
def test_parse_policy_rejects(text: str) -> None:
    with pytest.raises(ValueError, match="expected latest, fifo:N or ordered"):
        parse_policy(text)


DEFAULTS = config.Config().pools


@pytest.mark.parametrize(
    ("pools", "pool", "expected"),
    [
        # A pool named with one key keeps that pool's other defaults (issue 12, item 3).
        ({"vo": {"params": {"calibration": "calib.txt"}}}, "vo",
         {"policy": "ordered:16", "count": 1, "params": {"calibration": "calib.txt"}}),
        ({"vo": {"count": 0}}, "vo", {"policy": "ordered:16", "count": 0}),
        ({"mono": {"count": 3}}, "mono", {"policy": "latest", "nice": 5, "count": 3}),
        ({"stereo": {"policy": "fifo:4"}}, "stereo", {"policy": "fifo:4", "nice": 10}),
        # Pools the file does not name keep theirs.
        ({"vo": {"count": 0}}, "stereo", {"count": 1, "policy": "latest", "nice": 10}),
        ({"vo": {"count": 0}}, "tags", {"count": 0, "policy": "latest", "nice": 5}),
        ({}, "vo", {"count": 1, "policy": "ordered:16"}),
        # A new pool name starts from the generic pool defaults.
        ({"noop": {"count": 2}}, "noop", {"count": 2, "policy": "latest", "nice": 0}),
        ({"brightness": {"plugin": "m:C"}}, "brightness", {"plugin": "m:C", "count": 1}),
    ],
)
def test_pools_merge_over_defaults(
    pools: dict[str, object], pool: str, expected: dict[str, object]
) -> None:
    """Regression: a `pools:` section used to replace the whole default pool table."""
    cfg = config.from_data({"pools": pools}, "test.yaml")
    assert set(DEFAULTS) <= set(cfg.pools)
    got = msgspec.to_builtins(cfg.pools[pool])
    assert {k: got[k] for k in expected} == expected


@pytest.mark.parametrize(
    ("pools", "error"),
    [
        ({"vo": {"policy": "newest"}}, r"got 'newest' - at `\$.pools.vo.policy`"),
        ({"vo": {"policy": "fifo:0"}}, r"\$.pools.vo.policy`"),
        ({"vo": {"policy": 3}}, r"Expected `str`, got `int` - at `\$.pools.vo.policy`"),
        ({"vo": {"count": 2}}, "ordered policy takes count 0 or 1, got 2"),
        ({"vo": {"params": []}}, r"\$.pools.vo.params`"),
        ({"vo": {"affinity": [-1]}}, r"\$.pools.vo.affinity\[0\]`"),
        ({"vo": None}, r"Expected `object`, got `null` - at `\$.pools.vo`"),
        ({"mono": 3}, r"Expected `object`, got `int` - at `\$.pools.mono`"),
        ({"noop": {"colour": 1}}, r"unknown field `colour` - at `\$.pools.noop`"),
    ],
)
def test_merged_pool_errors_name_the_leaf_key(pools: dict[str, object], error: str) -> None:
    with pytest.raises(ConfigError, match=error):
        config.from_data({"pools": pools}, "test.yaml")


def test_workers_still_choose_which_pools_run_after_a_merge() -> None:
    cfg = config.from_data({"pools": {"vo": {"params": {"x": 1}}}}, "test.yaml")
    cfg = config.with_workers(cfg, {"vo": 1, "tags": 2}, ["vo", "tags"])
    assert {n: p.count for n, p in cfg.pools.items()} == {
        "mono": 0, "stereo": 0, "vo": 1, "tags": 2}
    assert cfg.pools["vo"].policy == "ordered:16"
    assert cfg.pools["vo"].params == {"x": 1}


def test_config_is_a_leaf_that_imports_no_runtime_module() -> None:
    """Pins the slip where config.py imported the events, outbox, health and policy modules
    (and through them messages, the modem codec and frames) for their section Structs."""
    import subprocess
    import sys

    code = ("import sys, trapflow.config.schema; "
            "print(' '.join(sorted(m for m in sys.modules if m.startswith('trapflow'))))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, timeout=60).stdout.split()
    assert [m for m in out if not m.startswith("trapflow.config.")] == [
        "trapflow", "trapflow.config", "trapflow.errors"]
    assert {"trapflow.config.schema", "trapflow.config.pools", "trapflow.config.modem"} <= set(out)


@pytest.mark.parametrize(("kind", "loop", "options", "waits"), [
    ("replay", False, {"rate": 0}, True),      # a replay as fast as it goes: paced by pools
    ("replay", False, {"rate": 0.0}, True),
    ("replay", False, {"rate": 1.0}, False),   # original timing: unchanged, pools may drop
    ("replay", False, {}, False),              # rate 1 is the default
    ("replay", True, {"rate": 0}, False),      # looped: endless, it keeps its clock
    ("replay", False, {"rate": "x"}, False),   # the source itself refuses it, clearly
    ("synthetic", False, {"rate": 0}, False),  # a live world is never held back
    ("images", False, {}, False),              # paced by source.rate_hz
])
def test_waits_for_pools(kind: str, loop: bool, options: dict[str, object],
                         waits: bool) -> None:
    """Regression (issue 22, item 2): which sources the broker holds back instead of
    dropping pairs in its pools."""
    assert SourceConfig(kind=kind, loop=loop, options=options).waits_for_pools is waits
