"""Who may tell the broker what, pure: a sender's identity and its message in, a verdict out.

The supervisor's orders (pool switch, ladder level, stopping notice, another worker's
death) come only on its own channel, sealed with the run's key (control_msgs.open_order
checks each); on the workers' socket, where every local worker and any process of the same
user could claim any identity, they are refused whoever sends them (issue 26 item 9: an
identity string let a same-user process switch a pool). Remote workers speak for a pool
only once their hello for it was taken. No sockets, no clocks: the broker shell counts a
refusal by its reason (refused_<reason>) and logs its line, rate-limited.
"""

from __future__ import annotations

from dataclasses import dataclass

from trapflow.broker.remote_state import RemoteWorkers
from trapflow.errors import ProtocolError, unreachable
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


_ORDERS_ONLY = "only the supervisor may send it, on its own channel"


def on_workers_socket(sender: bytes, msg: LocalMsg) -> Verdict:
    """A message from `sender` on the workers' socket (or a local worker's link, as the
    identity that link named itself with; a remote worker's, after on_remote_socket)."""
    if isinstance(msg, (Ready, Alive, Done, Failed)):
        # Any worker may; an answer is checked against what was dispatched to it by
        # BrokerState (a Rejected action), not here.
        return ALLOW
    elif isinstance(msg, Gone):
        # A worker tells of its own end here; of another's, only the supervisor's orders.
        if sender == msg.worker.encode():
            return ALLOW
        return Refuse("forged_gone", "refused a gone message for worker '%s' from '%s': "
                      "only that worker, or the supervisor on its own channel, may send it",
                      (wire(msg.worker), wire(sender)))
    elif isinstance(msg, Stopping):
        # It quiets the warnings of workers leaving: a worker must not be able to.
        return Refuse("forged_stopping", "refused a stopping notice from '%s': " + _ORDERS_ONLY,
                      (wire(sender),))
    elif isinstance(msg, PoolSwitch):
        return Refuse("forged_switch", "refused a pool switch for '%s' from '%s': "
                      + _ORDERS_ONLY, (wire(msg.pool), wire(sender)))
    elif isinstance(msg, LadderLevel):
        return Refuse("forged_level", "refused a ladder level '%s' from '%s': " + _ORDERS_ONLY,
                      (wire(msg.level), wire(sender)))
    else:
        unreachable(msg)


def local_msg(msg: WorkerMsg) -> LocalMsg:
    """Hello, JoinRequest and HostAlive belong to the remote socket; on a local path they
    are refused."""
    if isinstance(msg, (Hello, JoinRequest, HostAlive)):
        raise ProtocolError(f"worker message: expected ready, alive, done, failed or gone on "
                            f"a local path, got {type(msg).__name__} (remote workers connect "
                            f"to network.remote.bind)")
    return msg


def names_link(msg: LocalMsg) -> str | Refuse:
    """The worker name a local link takes from its first message. The supervisor is never
    on a link, so a link that opens with one of its messages is no worker: the shell counts
    it as malformed (a ProtocolError with this text), not as a refusal."""
    if isinstance(msg, (PoolSwitch, LadderLevel, Stopping)):
        return Refuse("malformed", "worker link: expected a worker message first, got a %s "
                      "(only the supervisor sends those, on its own channel)",
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
