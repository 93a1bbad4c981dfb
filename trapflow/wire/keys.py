"""CURVE key pairs for pipelines and remote workers, made by ZeroMQ's own tools
(zmq.auth.create_certificates); secret and public files are readable by their owner only."""

from __future__ import annotations

import os
from pathlib import Path

from trapflow.errors import ConfigError

KEY_MODE = 0o600
DIR_MODE = 0o700


def generate(folder: Path, name: str = "client") -> tuple[Path, Path]:
    """Write NAME.key (public) and NAME.key_secret into folder; never overwrite a key."""
    if not name or not name.replace("-", "_").isidentifier():
        raise ConfigError(f"--name: expected a file name of letters, digits, '-' or '_', "
                          f"got {name!r}")
    import zmq.auth

    public, secret = folder / f"{name}.key", folder / f"{name}.key_secret"
    for path in (public, secret):
        if path.exists():
            raise ConfigError(f"{path} exists: expected a folder without keys named {name!r}; "
                              f"remove them first or give another --name")
    old = os.umask(0o077)  # no moment where a secret key is readable by others
    try:
        folder.mkdir(parents=True, exist_ok=True, mode=DIR_MODE)
        made = zmq.auth.create_certificates(str(folder), name)
    finally:
        os.umask(old)
    for made_path in made:
        os.chmod(made_path, KEY_MODE)
    return Path(made[0]), Path(made[1])
