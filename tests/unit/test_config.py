"""Config tables: every shipped file validates, bad input names its key, CLI counts parse."""

from __future__ import annotations

from pathlib import Path

import msgspec
import pytest

from trapflow import config
from trapflow.errors import ConfigError
from trapflow.policy import Policy, parse_policy

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
        ("mono=0", None, "at least 1, got 'mono=0'"),
        ("mono=-2", None, "at least 1, got 'mono=-2'"),
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
