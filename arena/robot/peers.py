"""Who is attached to one robot: its master (at most one) and its slaves, as records. Pure.

This is the actor's bookkeeping of its peers, beside the safety table (`safety.py`) that decides
who may command: no trio, no I/O, no clock (times are given). The actor carries out what it
answers: it stops the driver of a peer that leaves, closes its link and publishes the change.

Ownership is decided once, by the safety table: `SafetyState.owner` names the master that may
command. The table here keeps that master's record (its link, its heartbeat) and lets it go by
one rule, `Peers.settle`: a master that the safety state no longer names as owner is gone. A master
displaced by another (a takeover, an autonomous master ended by an e-stop) goes by the safety
table's `DetachMaster` effect, which says why.

A record holds the link (`L`) through which the actor reaches its peer, whatever that is: the
actor keeps `MasterLink`s and `SlaveLink`s here, the tests plain values.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Awaitable, Callable, Iterator
from dataclasses import dataclass, field
from typing import Any, ClassVar, Generic, TypeVar

from arena.protocol.errors import ErrorCode, Severity
from arena.robot.events import FaultReported, PeerChanged
from arena.robot.snapshot import FaultSnapshot, PeerSnapshot

#: Faults a peer holds at once (a peer may be hostile: a WebSocket slave names its own codes and
#: joints); the oldest goes when another comes.
MAX_FAULTS = 16

#: Which faults of a peer (code, joint): None, every one.
FaultKeys = list[tuple[str, str | None]] | None

L = TypeVar("L")
M = TypeVar("M")
S = TypeVar("S")


@dataclass(eq=False, slots=True)
class Peer(Generic[L]):
    """An attached master or slave: what the robot knows of it and how it reaches it."""

    role: ClassVar[str]
    peer_id: str
    kind: str  # its driver's kind ("mock-slave", "websocket")
    link: L
    heartbeat_timeout: float | None  # None: it need not send heartbeats
    last_seen: float  # trio time the robot last heard from it
    #: Stops the driver the robot runs for this peer (None: the peer runs elsewhere).
    stop: Callable[[], None] | None = None
    #: The driver the robot runs for this peer (None: the peer runs elsewhere).
    driver: object | None = None
    #: Waits until that driver's `run` has returned: its hardware let go (None: no driver).
    closed: Callable[[], Awaitable[None]] | None = None
    #: Its faults that last, by (code, joint), oldest first: each one until its source says it
    #: is over, the robot is reset or the peer leaves (`fault`, `faults_over`).
    faults: dict[tuple[str, str | None], FaultSnapshot] = field(default_factory=dict)

    def deadline(self) -> float:
        """When it is lost unless heard from (inf: never)."""
        timeout = self.heartbeat_timeout
        return math.inf if timeout is None else self.last_seen + timeout

    def fault(
        self,
        robot_id: str,
        code: str,
        message: str,
        severity: Severity,
        joint: str | None,
        now: float,
        wall_time: float,
    ) -> FaultReported:
        """Keep a fault that lasts from `now` (the same code at the same joint replaces it,
        and is then the newest; at most `MAX_FAULTS`, the oldest goes); the event that tells
        it (to viewers and the recording)."""
        key = (code, joint)
        self.faults.pop(key, None)
        self.faults[key] = FaultSnapshot(code, message, str(severity), joint, now)
        while len(self.faults) > MAX_FAULTS:
            del self.faults[next(iter(self.faults))]
        return FaultReported(robot_id, self.peer_id, code, message, severity, joint, now, wall_time)

    def faults_over(
        self,
        robot_id: str,
        why: str,
        now: float,
        wall_time: float,
        keys: FaultKeys = None,
    ) -> list[FaultReported]:
        """The end of these faults, by (code, joint) (None: every one), each as an event
        (severity info: an end is news, not trouble); a fault it did not have is no news."""
        ended = []
        for code, joint in list(self.faults) if keys is None else keys:
            if self.faults.pop((code, joint), None) is not None:
                ended.append(
                    FaultReported(
                        robot_id,
                        self.peer_id,
                        code,
                        why,
                        Severity.INFO,
                        joint,
                        now,
                        wall_time,
                        True,
                    )
                )
        return ended

    def changed(
        self,
        robot_id: str,
        change: str,
        reason: str,
        now: float,
        wall_time: float,
        code: str | None = None,
    ) -> PeerChanged:
        """The event that says this peer `change`d ("attached", "lost", ...) and why (`code`:
        the error code a refused peer was told)."""
        autonomous = change == "attached" and isinstance(self, MasterPeer) and self.autonomous
        return PeerChanged(
            robot_id,
            self.role,
            self.peer_id,
            self.kind,
            change,
            reason,
            now,
            wall_time,
            autonomous,
            code,
        )

    def snapshot(self, joining: bool = False, paused: bool = False) -> PeerSnapshot:
        """The peer as `RobotSnapshot` shows it (`paused`: a master that waits)."""
        connected = self.connected if isinstance(self, SlavePeer) else True
        description = self.description if isinstance(self, MasterPeer) else ""
        faults = tuple(self.faults.values())
        error = f"{faults[-1].code}: {faults[-1].message}" if faults else None
        if isinstance(self, SlavePeer) and not self.connected:  # the loss, while it lasts
            error = f"{ErrorCode.SLAVE_LOST}: {self.out_of_reach}"
        figures = getattr(self.driver, "figures", None)  # (a driver's own, if it has any)
        return PeerSnapshot(
            self.peer_id, self.role, self.kind, connected, error, joining, description, faults,
            paused, None if figures is None else figures(),
        )  # fmt: skip


@dataclass(eq=False, slots=True)
class MasterPeer(Peer[L]):
    """The master: the source of the robot's commands."""

    role: ClassVar[str] = "master"
    autonomous: bool = False  # plays a program (sequence, replay): ends for good on e-stop
    description: str = ""  # what it is, in words ("sequence 'gentle-wave'")


@dataclass(eq=False, slots=True)
class SlavePeer(Peer[L]):
    """A slave: it executes the robot's targets and reports joint states."""

    role: ClassVar[str] = "slave"
    connected: bool = True  # False while the hardware behind it is out of reach
    out_of_reach: str = ""  # why it last went out of reach
    real: dict[str, float] = field(default_factory=dict)  # its newest measured values


class Peers(Generic[M, S]):
    """The master and slaves of one robot (`M`, `S`: what their records hold as links)."""

    def __init__(self) -> None:
        self.master: MasterPeer[M] | None = None
        #: The master an intervention paused (the safety state's `waiting`), kept until the
        #: intervention ends and it is the master again.
        self.waiting: MasterPeer[M] | None = None
        self.slaves: dict[str, SlavePeer[S]] = {}
        self._ids = itertools.count(1)

    def new_id(self, role: str) -> str:
        """An id for a peer that brought none ("slave-3")."""
        return f"{role}-{next(self._ids)}"

    def __iter__(self) -> Iterator[MasterPeer[M] | SlavePeer[S]]:
        """Every peer: the slaves, then the master."""
        yield from self.slaves.values()
        if self.master is not None:
            yield self.master
        if self.waiting is not None:
            yield self.waiting

    def add(self, peer: MasterPeer[M] | SlavePeer[S]) -> None:
        """Record a peer that attached (a master once the safety table let it claim the robot:
        it replaces none, a master it displaced was let go first)."""
        if isinstance(peer, MasterPeer):
            self.master = peer
        else:
            self.slaves[peer.peer_id] = peer

    def holds(self, peer: Peer[Any]) -> bool:
        """True while this very record is attached (a later peer may have its id)."""
        return peer is self.master or peer is self.waiting or self.slaves.get(peer.peer_id) is peer

    def remove(self, peer: Peer[Any]) -> bool:
        """Let `peer` go; False if it was not attached (any more), and nothing changes."""
        if peer is self.master:
            self.master = None
            return True
        if peer is self.waiting:
            self.waiting = None
            return True
        if self.slaves.get(peer.peer_id) is peer:
            del self.slaves[peer.peer_id]
            return True
        return False

    def master_named(self, master_id: str | None) -> MasterPeer[M] | None:
        """The master if it is `master_id` (None: whichever it is), else None."""
        master = self.master
        if master is None or (master_id is not None and master.peer_id != master_id):
            return None
        return master

    def either_named(self, master_id: str | None) -> MasterPeer[M] | None:
        """The master (else the paused master of an intervention) if it is `master_id`."""
        found = self.master_named(master_id)
        if found is None and master_id is not None:
            waiting = self.waiting
            if waiting is not None and waiting.peer_id == master_id:
                return waiting
        return found

    def intervene(self, peer: MasterPeer[M]) -> None:
        """`peer` intervenes: the master waits, `peer` is the master."""
        self.waiting, self.master = self.master, peer

    def hand_back(self) -> MasterPeer[M] | None:
        """The intervention ends: the waiting master is the master again; returns the
        intervening one (let go)."""
        intervening, self.master, self.waiting = self.master, self.waiting, None
        return intervening

    def settle(self, owner: str | None) -> MasterPeer[M] | None:
        """The master, let go, if the safety state's `owner` is no longer it; else None."""
        master = self.master
        if master is None or master.peer_id == owner:
            return None
        self.master = None
        return master

    def touch(self, peer_id: str, now: float) -> None:
        """Heard from `peer_id` at `now` (the master if both have that id)."""
        master = self.master
        if master is not None and master.peer_id == peer_id:
            master.last_seen = now
        elif (waiting := self.waiting) is not None and waiting.peer_id == peer_id:
            waiting.last_seen = now
        elif (slave := self.slaves.get(peer_id)) is not None:
            slave.last_seen = now

    def next_deadline(self) -> float:
        """The earliest heartbeat deadline of any peer (inf: none)."""
        deadline = math.inf  # (a plain loop: the actor asks before every message it takes)
        for peer in self.slaves.values():
            if peer.heartbeat_timeout is not None:
                deadline = min(deadline, peer.last_seen + peer.heartbeat_timeout)
        master = self.master
        if master is not None and master.heartbeat_timeout is not None:
            deadline = min(deadline, master.last_seen + master.heartbeat_timeout)
        waiting = self.waiting
        if waiting is not None and waiting.heartbeat_timeout is not None:
            deadline = min(deadline, waiting.last_seen + waiting.heartbeat_timeout)
        return deadline

    def timed_out(self, now: float) -> list[MasterPeer[M] | SlavePeer[S]]:
        """The peers whose heartbeat deadline has passed at `now`."""
        return [peer for peer in self if now >= peer.deadline()]
