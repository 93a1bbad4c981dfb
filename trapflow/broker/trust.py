"""Who may tell the broker what, pure: a sender's identity and its message in, a verdict out.

The supervisor's control messages (pool switch, ladder level, stopping notice, another
worker's death) ride the workers' socket, where every local worker could send them too;
only the identity of the supervisor's DEALER may. Remote workers may never send them, and
speak for a pool only once their hello for it was taken. No sockets, no clocks: the broker
shell counts a refusal by its reason (refused_<reason>) and logs its line, rate-limited.
"""

from __future__ import annotations

from dataclasses import dataclass

from trapflow.broker.remote_state import RemoteWorkers
from trapflow.errors import unreachable
from trapflow.runtime.ratelog import wire
from trapflow.wire.messages import (
    Alive,
    Done,
    Failed,
    Gone,
    Hello,
    HostAlive,
    JoinRequest,
    LadderLevel,
    PoolSwitch,
    Ready,
    Stopping,
    WorkerMsg,
)

SUPERVISOR_IDENT = b"supervisor"  # the supervisor's DEALER identity on the workers socket

# What may arrive on the workers' socket or a local link (the rest is the remote socket's).
LocalMsg = Ready | Alive | Done | Failed | Gone | PoolSwitch | LadderLevel | Stopping


@dataclass(frozen=True)
class Allow:
    """Apply the message."""


@dataclass(frozen=True)
class Refuse:
    """Apply nothing of it: counted as refused_<reason>, logged as message % args."""

    reason: str
    message: str
    args: tuple[object, ...] = ()

    def text(self) -> str:
        """The log line, formatted."""
        return self.message % self.args


Verdict = Allow | Refuse

ALLOW = Allow()


def _supervisor_only(sender: bytes, refusal: Refuse) -> Verdict:
    return ALLOW if sender == SUPERVISOR_IDENT else refusal


def on_workers_socket(sender: bytes, msg: LocalMsg) -> Verdict:
    """A message from `sender` on the workers' socket (or a local worker's link, as the
    identity that link named itself with; a remote worker's, after on_remote_socket)."""
    if isinstance(msg, (Ready, Alive, Done, Failed)):
        # Any worker may; an answer is checked against what was dispatched to it by
        # BrokerState (a Rejected action), not here.
        return ALLOW
    elif isinstance(msg, Gone):
        # Only the supervisor tells of another worker's death; a worker, of its own.
        if sender in (SUPERVISOR_IDENT, msg.worker.encode()):
            return ALLOW
        return Refuse("forged_gone", "refused a gone message for worker '%s' from '%s': "
                      "only the supervisor or that worker may send it",
                      (wire(msg.worker), wire(sender)))
    elif isinstance(msg, Stopping):
        # It quiets the warnings of workers leaving: a worker must not be able to.
        return _supervisor_only(sender, Refuse(
            "forged_stopping", "refused a stopping notice from '%s': only the supervisor "
            "may send it", (wire(sender),)))
    elif isinstance(msg, PoolSwitch):
        return _supervisor_only(sender, Refuse(
            "forged_switch", "refused a pool switch for '%s' from '%s': only the supervisor "
            "may send it", (wire(msg.pool), wire(sender))))
    elif isinstance(msg, LadderLevel):
        return _supervisor_only(sender, Refuse(
            "forged_level", "refused a ladder level '%s' from '%s': only the supervisor may "
            "send it", (wire(msg.level), wire(sender))))
    else:
        unreachable(msg)


def names_link(msg: LocalMsg) -> str | Refuse:
    """The worker name a local link takes from its first message. The supervisor is never
    on a link, so a link that opens with one of its messages is no worker: the shell counts
    it as malformed (a ProtocolError with this text), not as a refusal."""
    if isinstance(msg, (PoolSwitch, LadderLevel, Stopping)):
        return Refuse("malformed", "worker link: expected a worker message first, got a %s "
                      "(only the supervisor sends those, on the workers socket)",
                      (msg.__struct_config__.tag,))
    elif isinstance(msg, (Ready, Alive, Done, Failed, Gone)):
        return msg.worker
    else:
        unreachable(msg)


def _remote_name(sender: bytes) -> str:
    return wire(sender.decode("utf-8", "replace"))


def on_remote_socket(sender: bytes, msg: WorkerMsg, roster: RemoteWorkers) -> Verdict:
    """A message from `sender` on the remote workers' socket (network.remote.bind), given
    who joined (roster). What is allowed of a worker's messages is then judged again as on
    the workers' socket (on_workers_socket)."""
    if isinstance(msg, (JoinRequest, Hello)):
        return ALLOW  # the pool's config decides the welcome (trapflow.broker.remote)
    elif isinstance(msg, HostAlive):
        return ALLOW  # only a known owner's heartbeat is remembered (RemoteWorkers)
    elif isinstance(msg, Gone):
        if roster.may_report(sender, msg.worker.encode()):
            return ALLOW
        return Refuse("forged_gone", "refused a gone message for worker '%s' from remote "
                      "'%s': only that worker or its own supervisor may send it",
                      (wire(msg.worker), _remote_name(sender)))
    elif isinstance(msg, LadderLevel):
        return Refuse("forged_level", "refused a ladder level from remote '%s': only the "
                      "supervisor may send it", (_remote_name(sender),))
    elif isinstance(msg, Stopping):
        return Refuse("forged_stopping", "refused a stopping notice from remote '%s': only "
                      "the supervisor may send it", (_remote_name(sender),))
    elif isinstance(msg, (Ready, Alive, Done, Failed, PoolSwitch)):
        if roster.pool_of(sender) != msg.pool:
            return Refuse("remote_not_joined", "refused a message from remote '%s' for pool "
                          "'%s': expected a hello for that pool first",
                          (_remote_name(sender), wire(msg.pool)))
        return ALLOW
    else:
        unreachable(msg)
