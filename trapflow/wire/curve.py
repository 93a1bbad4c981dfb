"""CURVE: key files, the ZAP authenticator of a socket remote workers reach, and the handshake
monitor that says why a peer was refused."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import zmq

from trapflow.errors import StartupError
from trapflow.wire.transport import CurveKeys, zmq_readable

# --- CURVE: keys, the authenticator, the handshake monitor ------------------------------

SERVER_KEY_NAME = "server.key"  # the pipeline's public key, in a remote worker's key folder
CLIENT_SECRET_NAME = "client.key_secret"  # a remote worker's own key pair, in the same folder


def load_key_file(path: Path, secret: bool) -> tuple[bytes, bytes | None]:
    """(public, secret) from a key file made by zmq.auth; StartupError naming the fix."""
    import zmq.auth

    kind = "secret key file (NAME.key_secret)" if secret else "public key file (NAME.key)"
    if not path.is_file():
        raise StartupError(f"expected a CURVE {kind} at {path}, got no such file; make one "
                           f"with `trapflow keys generate DIR`")
    try:
        public, sec = zmq.auth.load_certificate(str(path))
    except (OSError, ValueError) as exc:
        raise StartupError(f"expected a CURVE {kind} at {path}, got: {exc}; "
                           f"make one with `trapflow keys generate DIR`") from None
    if secret and not sec:
        raise StartupError(f"expected a CURVE {kind} at {path}, got a public key only; "
                           f"give the .key_secret file of `trapflow keys generate`")
    return public, sec


def server_keys(secret_file: Path) -> CurveKeys:
    """The pipeline's CURVE server keys (network.remote.server_key)."""
    public, secret = load_key_file(secret_file, secret=True)
    assert secret is not None
    return CurveKeys(public, secret)


def client_keys(folder: Path) -> CurveKeys:
    """A remote worker's keys: its own pair and the pipeline's public key, in one folder."""
    public, secret = load_key_file(folder / CLIENT_SECRET_NAME, secret=True)
    server, _ = load_key_file(folder / SERVER_KEY_NAME, secret=False)
    assert secret is not None
    return CurveKeys(public, secret, server)


def start_authenticator(ctx: zmq.Context[zmq.Socket[bytes]], authorized: Path) -> Any:
    """ZAP for every CURVE server socket of ctx: only the public keys in `authorized` pass.

    zmq.auth's ThreadAuthenticator answers handshakes from a thread of its own; it sees
    keys, never frames.
    """
    from zmq.auth.thread import ThreadAuthenticator

    if not authorized.is_dir():
        raise StartupError(f"network.remote.authorized_keys: expected a folder of public "
                           f"keys (*.key), got {authorized} (not a folder)")
    auth = ThreadAuthenticator(ctx)
    auth.start()
    auth.configure_curve(domain="*", location=str(authorized))
    return auth


# Handshake failures of a CURVE server socket, as the reason they are counted under.
HANDSHAKE_REFUSALS = {
    int(zmq.EVENT_HANDSHAKE_FAILED_AUTH): "remote_unauthorised_key",
    int(zmq.EVENT_HANDSHAKE_FAILED_PROTOCOL): "remote_bad_handshake",
    int(zmq.EVENT_HANDSHAKE_FAILED_NO_DETAIL): "remote_bad_handshake",
}


def open_monitor(sock: zmq.Socket[bytes]) -> zmq.Socket[bytes]:
    """A PAIR socket that receives sock's refused handshakes (zmq's socket monitor)."""
    events = 0
    for ev in HANDSHAKE_REFUSALS:
        events |= ev
    mon: zmq.Socket[bytes] = sock.get_monitor_socket(events)
    mon.setsockopt(zmq.LINGER, 0)
    return mon


def read_monitor(mon: zmq.Socket[bytes]) -> list[str]:
    """The refusal reasons waiting on a monitor socket (never blocks)."""
    from zmq.utils.monitor import parse_monitor_message

    out: list[str] = []
    while zmq_readable(mon):
        event = parse_monitor_message(mon.recv_multipart())
        reason = HANDSHAKE_REFUSALS.get(int(event["event"]))
        if reason is not None:
            out.append(reason)
    return out
