"""The actor's carrying out of who masters the robot (`arena.robot.actor.Actor` is one): a
master that goes, one that is paused or resumed, an intervention that starts or ends, and the
events each publishes. Split off the actor for its length; it decides nothing (the safety
table has, `arena.robot.safety`)."""

from __future__ import annotations

import logging
import time as wallclock
from collections.abc import Callable
from typing import Any

from arena.protocol.errors import ErrorCode
from arena.robot import safety
from arena.robot.core import MANUAL_SOURCE, GuardStop, RobotCore
from arena.robot.episodes import Episodes
from arena.robot.events import (
    InterventionChanged,
    MasterNotice,
    MotionStopped,
    RobotEvent,
    TakenBy,
)
from arena.robot.links import MasterLink, SlaveLink
from arena.robot.peers import FaultKeys, MasterPeer, Peer, Peers, SlavePeer
from arena.robot.snapshot import MasterEnded

log = logging.getLogger("arena.robot.actor")

Master = MasterPeer[MasterLink]
Slave = SlavePeer[SlaveLink]


class MasterKeeping:
    """What the actor does when the safety table changes its masters."""

    robot_id: str
    core: RobotCore
    peers: Peers[MasterLink, SlaveLink]
    _publish: Callable[[RobotEvent], None]
    episodes: Episodes
    intervention_count: int
    last_master: MasterEnded | None
    last_stop: MotionStopped | None
    _stop_logged: float  # trio time a guard's stop was last logged

    def _displaced(self, effect: safety.DetachMaster, now: float) -> None:
        """A master displaced (a takeover, an e-stop that ends a program, an intervention's
        paused master that ends): the table says why."""
        master = self.peers.either_named(effect.master_id)
        if master is not None and self.peers.remove(master):
            by = effect.by
            taken_by = None if by is None else TakenBy(by.master_id, by.kind, by.description)
            self._master_gone(master, effect.code, effect.message, "detached", now, taken_by)

    def _pause_master(self, effect: safety.PauseMaster | safety.ResumeMaster, now: float) -> None:
        """Tell a master (its link, and through it its driver) that it is paused or resumed."""
        paused = isinstance(effect, safety.PauseMaster)
        master = self.peers.either_named(effect.master_id)
        if master is not None:
            master.link.set_paused(paused, now)
            change = "paused" if paused else "resumed"
            log.info("robot %s: master %s %s", self.robot_id, master.peer_id, change)
            self._peer_changed(master, change, "", now)

    def _guard_stopped(self, stop: GuardStop, now: float) -> None:
        """A motion the guard stopped on its way after accepting it: recorded, kept for the
        robot's details (`last_stop`), and told to the master that commanded it (a socket's
        `stopped`, a driver's `MasterLink.stops`)."""
        going = [
            f"{name} {value:.1f} (of {stop.goals[name]:.1f})"
            for name, value in stop.held.items()
            if stop.goals.get(name, value) != value
        ]
        message = (
            f"Stopped on the way by the collision guard: going on would have brought {stop.hit} "
            f"together; the arm holds at {', '.join(going) or 'where it was'}."
        )
        event = MotionStopped(
            self.robot_id,
            stop.source or MANUAL_SOURCE,
            str(ErrorCode.COLLISION),
            message,
            (stop.hit.first, stop.hit.second),
            stop.held,
            stop.goals,
            now,
            wallclock.time(),
        )
        self.last_stop = event
        if now - self._stop_logged >= 1.0:  # (a master pushing on at its rate: once a second)
            self._stop_logged = now
            log.warning("robot %s: %s (%s)", self.robot_id, message, event.source)
        self._publish(event)
        master = self.peers.either_named(stop.source)
        if master is not None:
            master.link.stops += 1
            master.link.last_stop = message
            blocked = (stop.hit.first, stop.hit.second)
            notice = MasterNotice("stopped", ErrorCode.COLLISION, message, blocked=blocked)
            master.link.notices.put(notice)

    def _intervention(self, effect: safety.Intervention, now: float) -> None:
        """An intervention starts (the attach records the peers) or ends: the intervening
        master goes, the paused one is the master again."""
        if effect.ended:
            intervening = self.peers.hand_back()
            if intervening is not None:
                reason = effect.message or "the intervention ended"
                self._master_gone(intervening, effect.code, reason, "released", now)
        change = "ended" if effect.ended else "started"
        if not effect.ended:  # a correction, counted in the episode it falls in
            self.intervention_count += 1
            self.episodes.corrected()
        log.info(
            "robot %s: intervention by %s %s (%s waits)",
            self.robot_id,
            effect.master_id,
            change,
            effect.paused,
        )
        self._publish(
            InterventionChanged(
                self.robot_id, change, effect.master_id, effect.paused, now, wallclock.time()
            )
        )

    def _settle_master(self, code: ErrorCode | None, reason: str, change: str, now: float) -> None:
        """After a master's own leaving was applied: if the safety state no longer names it as
        owner (`Peers.settle`), it is gone."""
        master = self.peers.settle(self.core.state.owner)
        if master is not None:
            self._master_gone(master, code, reason, change, now)

    def _master_gone(
        self,
        master: Master,
        code: ErrorCode | None,
        reason: str,
        change: str,
        now: float,
        by: TakenBy | None = None,
    ) -> None:
        """A master no longer attached: forgotten by the core, told why, its driver stopped."""
        self.core.forget_master(master.peer_id)
        link = master.link
        if code is not None:
            link.notices.put(MasterNotice("detached", code, reason, by=by))
        link.detached.set()
        link.notices.close()
        if master.stop is not None:
            master.stop()
        self.last_master = _ended(master, code, reason, change)
        self._faults_over(master, f"the master {change}", now)
        log.info("robot %s: master %s %s (%s)", self.robot_id, master.peer_id, change, reason)
        self._peer_changed(master, change, reason, now)

    def _faults_over(self, peer: Peer[Any], why: str, now: float, keys: FaultKeys = None) -> None:
        for event in peer.faults_over(self.robot_id, why, now, wallclock.time(), keys):
            self._publish(event)

    def _peer_changed(
        self, peer: Peer[Any], change: str, reason: str, now: float, code: str | None = None
    ) -> None:
        self._publish(peer.changed(self.robot_id, change, reason, now, wallclock.time(), code))


#: The faults that say why a master ended (a warning does not).
_SEVERE = frozenset({"error", "critical"})


def _ended(master: Master, code: ErrorCode | None, reason: str, change: str) -> MasterEnded:
    """What the details keep of a master that left (its faults end as it goes)."""
    severe = [f for f in master.faults.values() if str(f.severity) in _SEVERE]
    if severe:
        error: str | None = f"{severe[-1].code}: {severe[-1].message}"
    else:
        error = f"{code}: {reason}" if code is not None and change == "lost" else None
    kind, description = master.kind, master.description
    return MasterEnded(master.peer_id, kind, description, change, reason, error, wallclock.time())
