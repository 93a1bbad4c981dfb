"""Typed configuration: YAML decoded into Structs, unknown keys rejected, bounds checked.

Errors name the YAML path (`$.pools.vo.policy`) and what was expected. The
defaults here are the defaults; configs/default.yaml documents every key and a
test keeps the two equal; docs/config.md is generated from the fields' docs. The sections
live in a module per concern (capture, pools, outputs, power, runtime, modem, ladder; the
policy grammar in policy.py); this module composes them into Config, loads YAML and applies
the command line's overrides. A leaf: it imports only config modules, never a module of the
runtime; the runtime imports every section through this one name.
"""

from __future__ import annotations

from collections.abc import Collection
from pathlib import Path
from typing import Any, Literal

import msgspec
import yaml

from trapflow.config.base import Section
from trapflow.config.capture import DEFAULT_JPEG_QUALITY, FramesConfig, RigConfig, SourceConfig
from trapflow.config.image_health import ImageHealthConfig
from trapflow.config.ladder import LadderConfig
from trapflow.config.modem import HealthConfig, ModemConfig, OutboxConfig
from trapflow.config.outputs import (
    EventsConfig,
    ExportConfig,
    NormalizerConfig,
    ObserveConfig,
    RecordingConfig,
    TriggerRule,
)
from trapflow.config.policy import DEFAULT_ORDERED_BOUND, Policy, parse_policy
from trapflow.config.pools import PoolConfig, _default_pools
from trapflow.config.power import EnergyConfig, MotionGateConfig
from trapflow.config.review import LabelReview, ReviewConfig
from trapflow.config.runtime import (
    LogFileConfig,
    NetworkConfig,
    RemoteConfig,
    SupervisorConfig,
    ViewerConfig,
)
from trapflow.config.schedule import PowerConfig, ScheduleConfig
from trapflow.errors import ConfigError, yaml_problem


class Config(Section):
    """The whole pipeline."""

    source: SourceConfig = msgspec.field(default_factory=SourceConfig)
    rig: RigConfig = msgspec.field(default_factory=RigConfig)
    pools: dict[str, PoolConfig] = msgspec.field(default_factory=_default_pools)
    """One pool of worker processes per algorithm, by name; a pool a config names changes only the
    keys it gives (the defaults: mono, stereo, vo, tags)."""
    normalizer: NormalizerConfig = msgspec.field(default_factory=NormalizerConfig)
    observe: ObserveConfig = msgspec.field(default_factory=ObserveConfig)
    review: ReviewConfig = msgspec.field(default_factory=ReviewConfig)
    export: ExportConfig = msgspec.field(default_factory=ExportConfig)
    recording: RecordingConfig = msgspec.field(default_factory=RecordingConfig)
    energy: EnergyConfig = msgspec.field(default_factory=EnergyConfig)
    gate: MotionGateConfig = msgspec.field(default_factory=MotionGateConfig)
    schedule: ScheduleConfig = msgspec.field(default_factory=ScheduleConfig)
    power: PowerConfig = msgspec.field(default_factory=PowerConfig)
    supervisor: SupervisorConfig = msgspec.field(default_factory=SupervisorConfig)
    network: NetworkConfig = msgspec.field(default_factory=NetworkConfig)
    frames: FramesConfig = msgspec.field(default_factory=FramesConfig)
    outbox: OutboxConfig = msgspec.field(default_factory=OutboxConfig)
    modem: ModemConfig = msgspec.field(default_factory=ModemConfig)
    health: HealthConfig = msgspec.field(default_factory=HealthConfig)
    image_health: ImageHealthConfig = msgspec.field(default_factory=ImageHealthConfig)
    events: EventsConfig = msgspec.field(default_factory=EventsConfig)
    viewer: ViewerConfig = msgspec.field(default_factory=ViewerConfig)
    ladder: LadderConfig = msgspec.field(default_factory=LadderConfig)
    log_level: Literal["DEBUG", "INFO", "WARNING", "ERROR"] = "INFO"
    """Least level logged by every process to trapflow.log (standard error shows warnings
    and above)."""
    log_file: LogFileConfig = msgspec.field(default_factory=LogFileConfig)

    def __post_init__(self) -> None:
        for name, pool in self.pools.items():
            if not name.isidentifier():
                raise ValueError(f"pool name {name!r} must be an identifier")
            if pool.ordered and pool.count > 1:
                raise ValueError(
                    f"pool {name!r}: the ordered policy takes count 0 or 1, got {pool.count}"
                )
        if self.schedule.between == "poweroff" and self.power.wake == "none":
            raise ValueError("schedule.between: poweroff needs power.wake rtc or command "
                             "(with none the board would not wake again)")

    def validated(self) -> Config:
        """Re-run validation after programmatic changes."""
        return from_data(msgspec.to_builtins(self), "config")

    def plugin_of(self, pool: str) -> str:
        """The plugin name a pool runs."""
        return self.pools[pool].plugin or pool


def _pool_data(name: str, pool: Any) -> Any:
    """A user's pool merged key by key over that pool's defaults (a new name: PoolConfig's)."""
    if not isinstance(pool, dict):
        return pool  # not a mapping: left for msgspec to reject with the path
    default = _default_pools().get(name)
    base = msgspec.to_builtins(default) if default is not None else {}
    return {**base, **pool}


def _check_pool(name: str, pool: Any, origin: str) -> None:
    """Validate one pool so that errors name the pool's leaf key, not `$.pools[...]`."""
    policy = pool.get("policy") if isinstance(pool, dict) else None
    if isinstance(policy, str):
        try:
            parse_policy(policy)
        except ValueError as exc:
            raise ConfigError(f"{origin}: {exc} - at `$.pools.{name}.policy`") from None
    try:
        msgspec.convert(pool, PoolConfig, strict=True)
    except msgspec.ValidationError as exc:
        msg = str(exc).replace("`$", f"`$.pools.{name}")
        if "- at `$" not in msg:
            msg += f" - at `$.pools.{name}`"
        raise ConfigError(f"{origin}: {msg}") from None


def from_data(data: Any, origin: str = "config") -> Config:
    """Validate plain data (from YAML) into a Config; ConfigError names the bad key.

    A `pools:` section changes only what it names: each pool it gives is merged key by
    key over that pool's defaults, and the default pools it does not name stay as they are.
    """
    if data is None:
        data = {}
    pools = data.get("pools") if isinstance(data, dict) else None
    if isinstance(pools, dict):
        merged = {name: msgspec.to_builtins(p) for name, p in _default_pools().items()}
        for name, pool in pools.items():
            merged[name] = _pool_data(str(name), pool)
            _check_pool(str(name), merged[name], origin)
        data = {**data, "pools": merged}
    try:
        return msgspec.convert(data, Config, strict=True)
    except msgspec.ValidationError as exc:
        raise ConfigError(f"{origin}: {exc}") from None


def load(path: str | Path | None = None) -> Config:
    """Load a YAML config file, or the built-in defaults when path is None."""
    if path is None:
        return Config()
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"cannot read config {p}: {exc.strerror}") from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ConfigError(f"{p}: not valid YAML: {yaml_problem(exc)}") from None
    return from_data(data, str(p))


def parse_workers(text: str) -> dict[str, int]:
    """Parse `NAME=COUNT[,NAME=COUNT...]` into a dict; ConfigError names the bad part."""
    expected = "expected NAME=COUNT[,NAME=COUNT...]"
    counts: dict[str, int] = {}
    if not text.strip():
        raise ConfigError(f"{expected}, got an empty string")
    for part in text.split(","):
        name, sep, num = part.strip().partition("=")
        if not sep or not name.isidentifier():
            raise ConfigError(f"{expected}, got {part!r}")
        try:
            count = int(num)
        except ValueError:
            raise ConfigError(f"{expected} with an integer COUNT, got {part!r}") from None
        if count < 0:  # 0: a remote pool with no local worker (checked by with_workers)
            raise ConfigError(f"worker count must be 0 or more, got {part!r}")
        if name in counts:
            raise ConfigError(f"algorithm {name!r} given twice in {text!r}")
        counts[name] = count
    return counts


def with_workers(cfg: Config, counts: dict[str, int], known: list[str],
                 unlisted: Collection[str] = ()) -> Config:
    """Run exactly the named pools with these counts; others are switched off.

    A name that is not a configured pool but is a known plugin (or an unlisted one: the test
    kit's, accepted but never offered in the error) gets a default pool. A count of 0 names
    a remote pool that runs no local worker (its workers join from other hosts).
    """
    for name, count in counts.items():
        if count == 0 and not (name in cfg.pools and cfg.pools[name].remote):
            raise ConfigError(
                f"--workers {name}=0: a pool with no local worker needs workers from other "
                f"hosts; set pools.{name}.remote: true in the config, or give {name} a count "
                "of 1 or more, or leave it out")
    pools: dict[str, PoolConfig] = {}
    for name, pool in cfg.pools.items():
        pools[name] = msgspec.structs.replace(pool, count=counts.get(name, 0))
    for name, count in counts.items():
        if name not in pools:
            if name not in known and name not in unlisted:
                choices = ", ".join(sorted(set(known) | set(cfg.pools)))
                raise ConfigError(
                    f"unknown algorithm {name!r} in --workers: expected one of {choices}")
            pools[name] = PoolConfig(count=count)
    try:
        return msgspec.structs.replace(cfg, pools=pools).validated()
    except ValueError as exc:
        raise ConfigError(str(exc)) from None



def with_source(cfg: Config, **changes: Any) -> Config:
    """Override source fields (from command-line flags), re-validated."""
    if not changes:
        return cfg
    return msgspec.structs.replace(
        cfg, source=msgspec.structs.replace(cfg.source, **changes)
    ).validated()


def with_gate(cfg: Config, gate: bool) -> Config:
    """A re-analysis' config (`trapflow replay`): with `gate`, the config as it is (pools with
    `gate: motion` get only the pairs the motion gate lets through); without, every pool
    takes every pair (`gate: always`) and duty cycling is off, since a recording is
    re-analysed to see all of it (`--gate` asks for the gate)."""
    if gate:
        return cfg
    pools = {name: msgspec.structs.replace(p, gate="always") for name, p in cfg.pools.items()}
    return msgspec.structs.replace(
        cfg, pools=pools, gate=msgspec.structs.replace(cfg.gate, idle_after_s=0.0)
    ).validated()


def with_section(cfg: Config, section: str, **changes: Any) -> Config:
    """Override fields of one section (from command-line flags), re-validated."""
    if not changes:
        return cfg
    return msgspec.structs.replace(
        cfg, **{section: msgspec.structs.replace(getattr(cfg, section), **changes)}
    ).validated()


# The sections live in modules of their own; the runtime reads them through this one name.
__all__ = [
    "Config",
    "DEFAULT_JPEG_QUALITY",
    "DEFAULT_ORDERED_BOUND",
    "EnergyConfig",
    "EventsConfig",
    "ExportConfig",
    "FramesConfig",
    "HealthConfig",
    "LadderConfig",
    "LogFileConfig",
    "ModemConfig",
    "MotionGateConfig",
    "NetworkConfig",
    "NormalizerConfig",
    "ObserveConfig",
    "ReviewConfig",
    "LabelReview",
    "OutboxConfig",
    "Policy",
    "PoolConfig",
    "PowerConfig",
    "RecordingConfig",
    "RemoteConfig",
    "RigConfig",
    "ScheduleConfig",
    "Section",
    "SourceConfig",
    "SupervisorConfig",
    "TriggerRule",
    "ViewerConfig",
    "from_data",
    "load",
    "parse_policy",
    "parse_workers",
    "with_section",
    "with_source",
    "with_workers",
]
