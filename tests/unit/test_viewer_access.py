"""Who may use the viewer (trapflow.viewer.access, no sockets): Host names per bind, the
token's ways in, the token file's rules, and the config's documented defaults. Pins issue 26
item 2: reads answered any Host, and a bind off loopback asked for nothing; and issue 36
items 3 and 4: on loopback no token was asked (another local user read frames, switched a
pool off and stopped the pipeline), and the token rode on the node's state into the log,
`trapflow status` and /api/state."""

from __future__ import annotations

import socket
from pathlib import Path

import pytest

from trapflow.config import schema as configmod
from trapflow.config.schema import ViewerConfig
from trapflow.errors import ConfigError
from trapflow.viewer.access import (
    TOKEN_ENV,
    Access,
    Allow,
    Deny,
    SetCookie,
    allowed_hosts,
    bearer_of,
    console_address,
    host_name,
    load_token,
    make_access,
    new_token,
    public_address,
)

TOKEN = "t" * 32
REPO = Path(__file__).resolve().parents[2]
LOOP = Access(allowed_hosts("127.0.0.1", []), False, TOKEN)
LAN = Access(allowed_hosts("0.0.0.0", ["trap.lan"]), True, TOKEN)


@pytest.mark.parametrize(("access", "host", "path", "bearer", "cookie", "query", "want"), [
    # loopback: the loopback names, with or without port, with the token
    (LOOP, "127.0.0.1:8090", "/api/state", TOKEN, None, None, Allow()),
    (LOOP, "localhost:8090", "/metrics", None, TOKEN, None, Allow()),
    (LOOP, "[::1]:8090", "/", TOKEN, None, None, Allow()),
    (LOOP, "LOCALHOST.", "/", None, None, TOKEN, SetCookie("/")),
    # loopback without the token (another local user): reads and controls refused
    (LOOP, "127.0.0.1:8090", "/api/state", None, None, None, 401),
    (LOOP, "127.0.0.1:8090", "/frame/1/left.jpg", None, None, None, 401),
    (LOOP, "127.0.0.1:8090", "/api/stop", None, None, None, 401),
    (LOOP, "127.0.0.1:8090", "/api/pool", "x" * 32, None, None, 401),
    (LOOP, "127.0.0.1:8090", "/metrics", None, None, None, 401),
    # a rebinding page sends its own name: refused, reads like writes
    (LOOP, "evil.example:8090", "/api/state", None, None, None, 403),
    (LOOP, "evil.example", "/frame/1/left.jpg", None, None, None, 403),
    (LOOP, "localhost.evil.example", "/", None, None, None, 403),
    # on loopback only loopback addresses name it
    (LOOP, "192.168.1.20:8090", "/", None, None, None, 403),
    (LOOP, None, "/", None, None, None, 403),  # no Host at all
    # off loopback: the configured name, an IP literal, loopback (a tunnel), with the token
    (LAN, "trap.lan:8090", "/api/state", TOKEN, None, None, Allow()),
    (LAN, "192.168.1.20:8090", "/api/state", None, TOKEN, None, Allow()),
    (LAN, "[fe80::1]:8090", "/metrics", TOKEN, None, None, Allow()),
    (LAN, "localhost:8090", "/", None, TOKEN, None, Allow()),
    # a name not configured is refused before the token is looked at
    (LAN, "evil.example", "/api/state", TOKEN, TOKEN, None, 403),
    # no token, a wrong one, or a token in the query anywhere but the page: refused
    (LAN, "trap.lan", "/api/state", None, None, None, 401),
    (LAN, "trap.lan", "/api/state", "x" * 32, None, None, 401),
    (LAN, "trap.lan", "/", None, "x" * 32, "x" * 32, 401),
    (LAN, "trap.lan", "/api/state", None, None, TOKEN, 401),
    # the page loaded with ?token=: the cookie, and the address without it
    (LAN, "trap.lan:8090", "/", None, None, TOKEN, SetCookie("/")),
])
def test_access_decisions(access: Access, host: str | None, path: str, bearer: str | None,
                          cookie: str | None, query: str | None, want: object) -> None:
    got = access.decide(host, path, bearer, cookie, query)
    if isinstance(want, int):
        assert isinstance(got, Deny) and got.status == want, got
    else:
        assert got == want


@pytest.mark.parametrize(("header", "name"), [
    ("Example.ORG:80", "example.org"), ("[::1]:8090", "::1"), ("::1", "::1"),
    ("localhost.", "localhost"), ("", ""), ("[::1", "::1"),
])
def test_host_name(header: str, name: str) -> None:
    assert host_name(header) == name


def test_hosts_per_bind() -> None:
    own = socket.gethostname().lower()
    assert allowed_hosts("127.0.0.1", []) == {"127.0.0.1", "localhost", "::1"}
    assert allowed_hosts("localhost", ["Cam.Local"]) == {"127.0.0.1", "localhost", "::1",
                                                         "cam.local"}
    lan = allowed_hosts("192.168.1.20", [])
    assert {"192.168.1.20", own, f"{own}.local", "localhost"} <= lan


def test_make_access_per_bind(tmp_path: Path) -> None:
    """Every bind asks for a token: the one made by the process that prints it, or the
    operator's token file's."""
    token = "a-token-of-this-test-0123"
    loop = make_access("127.0.0.1", [], "", token)
    assert loop.token == token and not loop.any_ip
    assert make_access("0.0.0.0", [], "", token).any_ip
    f = tmp_path / "token"
    f.write_text(TOKEN + "\n")
    f.chmod(0o600)
    assert make_access("::", [], str(f), token).token == TOKEN
    with pytest.raises(ConfigError, match="at least 16"):
        make_access("127.0.0.1", [], "", "")


def test_a_new_token_is_random_unless_the_environment_gives_one(
        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(TOKEN_ENV, raising=False)
    one, two = new_token(), new_token()
    assert one != two and len(one) >= 32
    monkeypatch.setenv(TOKEN_ENV, TOKEN)
    assert new_token() == TOKEN
    monkeypatch.setenv(TOKEN_ENV, "short")
    with pytest.raises(ConfigError, match=f"{TOKEN_ENV}: expected at least 16"):
        new_token()


def test_the_token_is_on_the_console_only(tmp_path: Path) -> None:
    """The address the node's state (and so the log, status and /api/state) carries says
    where the token is; the console's has the token, or names the operator's own file."""
    token = new_token()
    public = public_address("http://127.0.0.1:8090/", "")
    assert token not in public and "console" in public
    assert console_address(public, token) == f"http://127.0.0.1:8090/?token={token}"
    own = tmp_path / "mine"
    line = console_address(public_address("http://h:1/", str(own)), token)
    assert token not in line and str(own) in line
    assert console_address("http://h:1/", token) == "http://h:1/"


@pytest.mark.parametrize(("mode", "content", "error"), [
    (0o600, TOKEN, None),
    (0o644, TOKEN, "readable by group or others"),
    (0o600, "short", "at least 16"),
    (0o600, "with a space in it, long enough", "without spaces"),
])
def test_token_file_rules(tmp_path: Path, mode: int, content: str, error: str | None) -> None:
    f = tmp_path / "token"
    f.write_text(content)
    f.chmod(mode)
    if error is None:
        assert load_token(f) == content
    else:
        with pytest.raises(ConfigError, match=error):
            load_token(f)


def test_missing_token_file_is_a_config_error(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="expected a readable text file"):
        load_token(tmp_path / "none")


@pytest.mark.parametrize(("header", "token"), [
    ("Bearer abc", "abc"), ("bearer  abc ", "abc"), ("Basic abc", None), ("Bearer ", None),
    (None, None),
])
def test_bearer_of(header: str | None, token: str | None) -> None:
    assert bearer_of(header) == token


def test_default_yaml_documents_the_viewer_access_defaults() -> None:
    """configs/default.yaml's viewer.allowed_hosts and token_file are the built-in defaults."""
    shipped = configmod.load(REPO / "configs" / "default.yaml").viewer
    assert shipped.allowed_hosts == ViewerConfig().allowed_hosts == []
    assert shipped.token_file == ViewerConfig().token_file == ""
