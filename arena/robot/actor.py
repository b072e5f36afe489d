"""The robot actor: one trio task that owns one robot's state.

Everything that can change the robot arrives as a message on its bounded inbox and is handled
in order by `Actor.run`, one handler per message type (`Actor._handlers`). Handling never
blocks: decisions come from the pure `RobotCore`, who is attached from the pure `Peers`, targets
go to per-slave `LatestMailbox`es, events to observers' `EventQueue`s. Master and slave drivers
run in the actor's own nursery, each in a cancel scope: a driver that raises is detached,
reported, and the loss policy applies; nothing else is disturbed.

The public face is `arena.robot.handle.Robot`, which posts messages here and waits for the
answers; in the actor's idle turn (`arena.robot.idle`) it calls `decide` and `apply` directly.
"""

from __future__ import annotations

import collections
import contextlib
import logging
import math
import time as wallclock
from collections.abc import Callable, Iterable
from typing import Any

import trio

from arena.protocol.errors import ArenaError, ErrorCode, Severity
from arena.robot import inbox, safety
from arena.robot.core import MANUAL_SOURCE, JoinChange, RobotCore, Step
from arena.robot.episodes import Episode, Episodes
from arena.robot.events import (
    CommandHandled,
    EpisodeChanged,
    FaultReported,
    JointStatesReceived,
    MasterNotice,
    MotionStopped,
    NoticeKind,
    RobotEvent,
    SlaveNotice,
    SlaveTarget,
    StateChanged,
    TargetsSent,
)
from arena.robot.idle import IdleTurn
from arena.robot.inbox import Driver, Msg
from arena.robot.links import MasterLink, RobotPort, SlaveLink
from arena.robot.mailbox import Observers
from arena.robot.motion import Command, CommandResult
from arena.robot.ownership import Master, MasterKeeping, Slave
from arena.robot.peers import MasterPeer, Peers, SlavePeer
from arena.robot.snapshot import MasterEnded

log = logging.getLogger(__name__)


class Actor(MasterKeeping):
    """The loop of one robot and the carrying out of its decisions (see the module)."""

    def __init__(
        self,
        robot_id: str,
        core: RobotCore,
        port: RobotPort,
        channel: tuple[trio.MemorySendChannel[Msg], trio.MemoryReceiveChannel[Msg]],
        turn: IdleTurn,
    ) -> None:
        self.robot_id = robot_id
        self.core = core
        self.model = core.model
        self._port = port  # what the links are given (and the way a driver's end is posted)
        self._send, self._receive = channel  # the inbox's two ends
        self.turn = turn
        self.peers: Peers[MasterLink, SlaveLink] = Peers()
        #: Measured joint values, by joint name (the newest of any slave).
        self.real: dict[str, float] = {}
        self.observers: Observers[RobotEvent] = Observers()
        self._publish = self.observers.publish
        #: When the next control tick is due (None: nothing moves).
        self.next_tick: float | None = None
        self._nursery: trio.Nursery | None = None
        self.stopped = trio.Event()
        #: Commands answered, by outcome: "accepted" or the refusal code (for metrics).
        self.command_counts: collections.Counter[str] = collections.Counter()
        self.estop_count = 0
        self.intervention_count = 0  # interventions started (corrections)
        self.last_master: MasterEnded | None = None  # the last master that left, and why
        self.last_stop: MotionStopped | None = None  # the last motion the guard stopped
        self._stop_logged = -math.inf
        self._superseded_by_gone = 0  # targets superseded at slaves that have left
        #: Data-collection episodes (changed only through `EpisodeMsg`).
        self.episodes = Episodes()
        # One handler per message type (a `ShutdownMsg` ends the loop: `_loop` takes it).
        self._handlers: dict[type, Callable[[Any, float], None]] = {
            inbox.CommandMsg: self._on_command,
            inbox.StatesMsg: self._on_states,
            inbox.EventMsg: self._on_event,
            inbox.AttachMsg: self._on_attach,
            inbox.DetachMsg: self._on_detach,
            inbox.FaultMsg: self._on_fault,
            inbox.AliveMsg: self._on_alive,
            inbox.LinkMsg: self._on_link,
            inbox.RejoinMsg: self._on_rejoin,
            inbox.DriverEndedMsg: self._on_driver_ended,
            inbox.WorkspaceMsg: self._on_workspace,
            inbox.EpisodeMsg: self._on_episode,
            inbox.SensorFaultMsg: self._on_sensor_fault,
        }

    @property
    def targets_superseded(self) -> int:
        """Targets a newer one replaced before a slave took it."""
        current = sum(peer.link.mailbox.coalesced for peer in self.peers.slaves.values())
        return self._superseded_by_gone + current

    # -- the loop -----------------------------------------------------------------------------

    async def run(self, *, task_status: Any = trio.TASK_STATUS_IGNORED) -> None:
        """The actor loop. Runs until a `ShutdownMsg` (or cancellation)."""
        try:
            async with trio.open_nursery() as nursery:
                self._nursery = nursery
                task_status.started()
                try:
                    await self._loop()
                finally:
                    # Refuse what comes now, before waiting for the drivers: one that is
                    # shielded while it waits for an answer would otherwise wait forever.
                    self._stop_taking_messages()
                nursery.cancel_scope.cancel()
        finally:
            self._nursery = None
            self._stop_taking_messages()
            self.observers.close()
            self.stopped.set()

    async def _loop(self) -> None:
        handlers, turn = self._handlers, self.turn
        while True:
            message: Msg | None = None
            with trio.move_on_at(self.deadline()) as wait:
                if not self._receive.statistics().current_buffer_used:
                    turn.open(wait)  # idle: a caller may take this turn (`arena.robot.idle`)
                try:
                    message = await self._receive.receive()
                finally:
                    turn.close()
            now = trio.current_time()
            if message is None:
                self._on_timers(now)
            elif type(message) is inbox.ShutdownMsg:
                self._on_shutdown(message.reason)
                if message.reply is not None:
                    message.reply.set(None)
                return
            else:
                handlers[type(message)](message, now)

    def deadline(self) -> float:
        """When the loop wakes by itself: the next tick, or a peer's heartbeat deadline."""
        tick = self.next_tick
        return min(math.inf if tick is None else tick, self.peers.next_deadline())

    def _stop_taking_messages(self) -> None:
        self.turn.close()
        self._send.close()
        error = ArenaError(ErrorCode.ROBOT_STOPPED, f"Robot {self.robot_id!r} has stopped.")
        while True:
            try:
                message = self._receive.receive_nowait()
            except (trio.WouldBlock, trio.EndOfChannel, trio.ClosedResourceError):
                return
            reply = getattr(message, "reply", None)
            if reply is not None:
                reply.fail(error)

    # -- decisions, also taken in the idle turn -----------------------------------------------

    def decide(
        self, source: str | None, command: Command, in_burst: bool, now: float
    ) -> CommandResult:
        """A command decided, counted, published and its targets sent."""
        if source is not None:
            self.peers.touch(source, now)
        result, step = self.core.command(source, command, now, in_burst=in_burst)
        self.command_counts["accepted" if result.accepted else str(result.code)] += 1
        self._publish(
            CommandHandled(
                self.robot_id, source or MANUAL_SOURCE, command, result, now, wallclock.time()
            )
        )
        if (stop := self.core.take_stop()) is not None:  # (its own first step)
            self._guard_stopped(stop, now)
        self._send_targets(step.targets, now, more_follow=in_burst)
        if step.joins:
            self._carry_out_joins(step.joins, now)
        return result

    def apply(self, event: safety.Event, now: float, cause: str) -> safety.Outcome:
        """A safety event through the core, its effects carried out, a change published."""
        before = self.core.state
        step = self.core.handle(event, now)
        self._carry_out(step, now)
        after = self.core.state
        changed = before.mode, before.owner, before.waiting, before.estop_reason
        if changed != (after.mode, after.owner, after.waiting, after.estop_reason):
            self._state_changed(cause, now)
        return step.outcome

    # -- handlers -----------------------------------------------------------------------------

    def _on_command(self, message: inbox.CommandMsg, now: float) -> None:
        result = self.decide(message.source, message.command, message.in_burst, now)
        if message.reply is not None:
            message.reply.set(result)

    def _on_event(self, message: inbox.EventMsg, now: float) -> None:
        outcome = self.apply(message.event, now, cause=type(message.event).__name__)
        if message.reply is not None:
            message.reply.set(outcome)

    def _on_alive(self, message: inbox.AliveMsg, now: float) -> None:
        self.peers.touch(message.peer_id, now)

    def _on_workspace(self, message: inbox.WorkspaceMsg, now: float) -> None:
        self.core.workspace = message.workspace  # checked from the next command on
        message.reply.set(None)

    def _on_sensor_fault(self, message: inbox.SensorFaultMsg, now: float) -> None:
        # A peer's own (a policy master's) is kept on it, a camera's not; neither stops it.
        m = message
        peer = self.peers.either_named(m.sensor_id) or self.peers.slaves.get(m.sensor_id)
        rid, told = self.robot_id, (m.code, m.message, m.severity, None, now, wallclock.time())
        self._publish(peer.fault(rid, *told) if peer else FaultReported(rid, m.sensor_id, *told))

    def _on_states(self, message: inbox.StatesMsg, now: float) -> None:
        peer = self.peers.slaves.get(message.slave_id)
        if peer is None:
            return
        peer.last_seen = now
        joints: dict[str, float] = {}
        for name, value in message.joints.items():
            spec = self.model.joint(name)
            if spec is not None and isinstance(value, int | float) and math.isfinite(value):
                joints[spec.name] = float(value)
        if not joints:
            return
        peer.real.update(joints)
        self.real.update(joints)
        self._publish(
            JointStatesReceived(self.robot_id, message.slave_id, joints, now, wallclock.time())
        )
        if message.slave_id in self.core.joining or message.slave_id in self.core.unsure:
            self._carry_out_joins(self.core.slave_measured(message.slave_id, joints, now), now)

    def _on_fault(self, message: inbox.FaultMsg, now: float) -> None:
        # A master's and a slave's alike: kept on the peer and told, until it ends.
        m, peers = message, self.peers
        peer = peers.either_named(m.peer_id) if m.role == "master" else peers.slaves.get(m.peer_id)
        if peer is None:
            return
        peer.last_seen = now
        joint = self.model.joint(m.joint) if m.joint else None
        name = joint.name if joint else m.joint
        if m.cleared:
            self._faults_over(peer, m.message or "cleared", now, [(m.code, name)])
            return
        self._publish(
            peer.fault(self.robot_id, m.code, m.message, m.severity, name, now, wallclock.time())
        )
        if isinstance(peer, SlavePeer):  # a master's faults never stop the robot by themselves
            self.apply(safety.SlaveError(m.peer_id, m.severity, m.message), now, cause=m.code)

    def _on_episode(self, message: inbox.EpisodeMsg, now: float) -> None:
        try:
            episode = self.episodes.act(
                message.action, message.task, now, message.since, message.keep
            )
        except ArenaError as refusal:
            message.reply.fail(refusal)
            return
        if message.action == "highlight":
            # Marked where it began, in the past: the recording and export sort by time.
            self._episode_changed("start", episode, now, episode.started)
            self._episode_changed("stop", episode, now)
        else:
            self._episode_changed(message.action, episode, now)
        message.reply.set(episode)

    def _episode_changed(
        self, change: str, episode: Episode, now: float, at: float | None = None
    ) -> None:
        """Publish an episode's change, stamped `at` (default: now)."""
        index, task, started = episode.index, episode.task, episode.started
        at = now if at is None else at
        wall = wallclock.time() - (now - at)
        changed = EpisodeChanged(self.robot_id, change, index, task, started, at, wall)
        self._publish(changed)

    def _on_link(self, message: inbox.LinkMsg, now: float) -> None:
        peer = self.peers.slaves.get(message.slave_id)
        if peer is None or peer.connected == message.connected:
            return
        peer.connected = message.connected
        change = "reconnected" if message.connected else "disconnected"
        level = logging.INFO if message.connected else logging.WARNING
        log.log(
            level, "robot %s: slave %s %s (%s)", self.robot_id, peer.peer_id, change, message.reason
        )
        self._peer_changed(peer, change, message.reason, now)
        if not message.connected:
            peer.out_of_reach = message.reason  # shown as its error while it lasts
            self.apply(safety.SlaveLost(peer.peer_id, message.reason), now, cause=message.reason)
        else:
            self.core.slave_rejoins(peer.peer_id)  # its arm may have been moved meanwhile

    def _on_rejoin(self, message: inbox.RejoinMsg, now: float) -> None:
        peer = self.peers.slaves.get(message.slave_id)
        if peer is None:
            return
        log.info("robot %s: slave %s joins again (%s)", self.robot_id, peer.peer_id, message.reason)
        self.core.slave_rejoins(peer.peer_id)
        if message.joints:
            joints = {
                spec.name: float(value)
                for name, value in message.joints.items()
                if (spec := self.model.joint(name)) is not None and math.isfinite(value)
            }
            self._carry_out_joins(self.core.slave_measured(peer.peer_id, joints, now), now)

    def _on_attach(self, message: inbox.AttachMsg, now: float) -> None:
        peer_id = message.peer_id or self.peers.new_id(message.role)
        peer: Master | Slave
        if message.role == "master":
            peer = MasterPeer(
                peer_id,
                message.kind,
                MasterLink(self._port, peer_id),
                message.heartbeat_timeout,
                now,
                autonomous=message.autonomous,
                description=message.description,
            )
            claim: safety.Event = (
                safety.Intervene(peer_id, message.autonomous, message.kind, message.description)
                if message.intervene
                else safety.MasterAttach(
                    peer_id, message.autonomous, message.takeover, message.kind, message.description
                )
            )
            outcome = self.apply(
                claim, now, cause="intervention" if message.intervene else "master attach"
            )
            if isinstance(outcome, safety.Refused):
                log.info("robot %s: master %s refused (%s)", self.robot_id, peer_id, outcome.code)
                self._peer_changed(peer, "refused", outcome.message, now, str(outcome.code))
                message.reply.fail(ArenaError(outcome.code, outcome.message))
                return
        else:
            if peer_id in self.peers.slaves:
                taken = f"A slave called {peer_id!r} is attached already."
                message.reply.fail(ArenaError(ErrorCode.INVALID_CONFIG, taken))
                return
            link = SlaveLink(self._port, peer_id)
            peer = SlavePeer(peer_id, message.kind, link, message.heartbeat_timeout, now)
            self.apply(safety.SlaveAttach(peer_id), now, cause="slave attach")
            driver = message.driver
            self.core.slave_attached(
                peer_id,
                # A slave over the network says by reporting (None: not known yet).
                measures=None if driver is None else getattr(driver, "measures", True),
                join_speed=getattr(driver, "join_speed", None),
            )
        if isinstance(peer, MasterPeer) and message.intervene:
            self.peers.intervene(peer)  # the master it paused waits
        else:
            self.peers.add(peer)
            if getattr(message.driver, "eases_in", False):  # (an intervening one always is)
                self.core.ease_in(peer_id)
        if message.driver is not None:
            scope = trio.CancelScope()
            closed = trio.Event()
            peer.stop = scope.cancel
            peer.driver = message.driver
            peer.closed = closed.wait
            assert self._nursery is not None
            self._nursery.start_soon(self._run_driver, peer, message.driver, scope, closed)
        log.info("robot %s: %s %s attached (%s)", self.robot_id, peer.role, peer_id, peer.kind)
        self._peer_changed(peer, "attached", "", now)
        message.reply.set(peer.link)

    def _on_detach(self, message: inbox.DetachMsg, now: float) -> None:
        if message.role == "master":
            master = self.peers.either_named(message.peer_id)
            if master is None:
                if message.reply is not None:
                    message.reply.set(None)  # not the master (any more): nothing to do
                return
            event: safety.Event = (
                safety.MasterLost(master.peer_id, message.reason)
                if message.lost
                else safety.MasterDetach(master.peer_id, message.hold)
            )
            self.apply(event, now, cause=message.reason)
            change = "lost" if message.lost else "released" if message.released else "detached"
            code = ErrorCode.MASTER_LOST if message.lost else None
            self._settle_master(code, message.reason, change, now)
        else:
            slave = self.peers.slaves.get(message.peer_id or "")
            if slave is None:
                unknown = f"No slave {message.peer_id!r} on this robot."
                if message.reply is not None:
                    message.reply.fail(ArenaError(ErrorCode.UNKNOWN_SLAVE, unknown))
                return
            self._drop_slave(slave, message.reason, lost=message.lost, now=now)
        if message.reply is not None:
            message.reply.set(None)

    def _on_driver_ended(self, message: inbox.DriverEndedMsg, now: float) -> None:
        peer = message.peer
        if not self.peers.holds(peer):
            return  # already detached by the robot
        error = message.error
        if error is not None:
            text = f"{type(error).__name__}: {error}"
            what = f"{peer.role} driver {peer.peer_id}"
            log.error("robot %s: %s failed: %s", self.robot_id, what, text, exc_info=error)
            failed = (ErrorCode.DRIVER_FAILED, text, Severity.ERROR, None, now, wallclock.time())
            self._publish(peer.fault(self.robot_id, *failed))  # (it ends as the peer goes)
        reason = "driver failed" if error else "driver finished"
        if isinstance(peer, MasterPeer):
            event: safety.Event = (
                safety.MasterLost(peer.peer_id, reason)
                if error
                else safety.MasterDetach(peer.peer_id, hold=False)  # its last move completes
            )
            self.apply(event, now, cause=reason)
            code = ErrorCode.DRIVER_FAILED if error else None
            self._settle_master(code, reason, "lost" if error else "detached", now)
        else:
            self._drop_slave(peer, reason, lost=error is not None, now=now)

    def _on_timers(self, now: float) -> None:
        if self.next_tick is not None and now >= self.next_tick:
            self.next_tick = None
            self._send_targets(self.core.tick(now), now)
            if (stop := self.core.take_stop()) is not None:
                self._guard_stopped(stop, now)
            self._carry_out_joins(self.core.advance_joins(now), now)
        for peer in self.peers.timed_out(now):
            log.warning(
                "robot %s: %s %s missed its heartbeat", self.robot_id, peer.role, peer.peer_id
            )
            if isinstance(peer, MasterPeer):
                self.apply(safety.HeartbeatTimeout(peer.peer_id), now, cause="heartbeat timeout")
                self._settle_master(ErrorCode.MASTER_LOST, "heartbeat timeout", "lost", now)
            else:
                self._drop_slave(peer, "heartbeat timeout", lost=True, now=now)

    def _on_shutdown(self, reason: str) -> None:
        now = trio.current_time()
        cut = self.episodes.cut(now)  # nobody stopped it: recorded as cut
        if cut is not None:
            self._episode_changed("cut", cut, now)
        for _ in range(2):  # an intervening master, then the master it had paused
            master = self.peers.master
            if master is None:
                break
            self.apply(safety.MasterDetach(master.peer_id), now, cause=reason)
            self._settle_master(ErrorCode.ROBOT_STOPPED, reason, "detached", now)
        for slave in list(self.peers.slaves.values()):
            self._drop_slave(slave, reason, lost=False, now=now)
        log.info("robot %s: stopped (%s)", self.robot_id, reason)

    # -- effects ------------------------------------------------------------------------------

    def _carry_out(self, step: Step, now: float) -> None:
        self._send_targets(step.targets, now)
        self._carry_out_joins(step.joins, now)
        for effect in step.effects:
            if isinstance(effect, safety.DetachMaster):
                self._displaced(effect, now)
            elif isinstance(effect, safety.StopMotion):
                self.estop_count += 1
                log.warning("robot %s: e-stop (%s)", self.robot_id, effect.reason)
                self._notify_slaves(SlaveNotice(NoticeKind.ESTOP, effect.reason), clears=True)
            elif isinstance(effect, safety.HoldPosition):
                self._notify_slaves(SlaveNotice(NoticeKind.HOLD, "holding position"))
            elif isinstance(effect, safety.PauseMaster | safety.ResumeMaster):
                self._pause_master(effect, now)
            elif isinstance(effect, safety.Intervention):
                self._intervention(effect, now)
            elif isinstance(effect, safety.ResumeSlaves):
                log.info("robot %s: reset", self.robot_id)
                # Every fault ends (a driver reports again what lasts: a servo still hot).
                for peer in self.peers:
                    self._faults_over(peer, "cleared by the reset", now)
                self._notify_slaves(SlaveNotice(NoticeKind.RESET, "e-stop reset"))
        self.next_tick = self.core.reschedule(self.next_tick, now)

    def _send_targets(
        self, targets: dict[str, float] | None, now: float, *, more_follow: bool = False
    ) -> None:
        if targets is not None:
            target = SlaveTarget(targets, now, more_follow)
            joining = self.core.joining  # they get targets of their own (`_carry_out_joins`)
            for slave in self.peers.slaves.values():
                if not joining or slave.peer_id not in joining:
                    slave.link.mailbox.put_target(target)
            self._publish(TargetsSent(self.robot_id, targets, now, wallclock.time()))
        self.next_tick = self.core.reschedule(self.next_tick, now)

    def _carry_out_joins(self, changes: Iterable[JoinChange], now: float) -> None:
        """Send joining slaves their own targets, the robot's an adopted pose; report each
        change of a join as a `PeerChanged` (recorded)."""
        for change in changes:
            if change.robot_targets is not None:
                self._send_targets(change.robot_targets, now)
            peer = self.peers.slaves.get(change.slave_id)
            if peer is None:
                continue
            if change.targets is not None:
                peer.link.mailbox.put_target(SlaveTarget(change.targets, now))
            if change.change is not None:
                log.info(
                    "robot %s: slave %s %s (%s)",
                    self.robot_id,
                    peer.peer_id,
                    change.change,
                    change.reason,
                )
                self._peer_changed(peer, change.change, change.reason, now)
        self.next_tick = self.core.reschedule(self.next_tick, now)

    def _notify_slaves(self, notice: SlaveNotice, clears: bool = False) -> None:
        for slave in self.peers.slaves.values():
            slave.link.mailbox.put_notice(notice, clears=clears)

    def _state_changed(self, cause: str, now: float) -> None:
        state = self.core.state
        self._publish(
            StateChanged(
                self.robot_id,
                state.mode,
                state.owner,
                state.estop_reason,
                cause,
                now,
                wallclock.time(),
            )
        )
        master = self.peers.master
        if master is not None:
            master.link.notices.put(MasterNotice("state", None, cause, state.mode))

    def _drop_slave(self, slave: Slave, reason: str, *, lost: bool, now: float) -> None:
        if not self.peers.remove(slave):
            return
        self.core.slave_detached(slave.peer_id)
        mailbox = slave.link.mailbox
        self._superseded_by_gone += mailbox.coalesced
        mailbox.put_notice(SlaveNotice(NoticeKind.SHUTDOWN, reason), clears=True)
        mailbox.close()
        if slave.stop is not None:
            slave.stop()
        change = "lost" if lost else "detached"
        self._faults_over(slave, f"the slave {change}", now)
        level = logging.WARNING if lost else logging.INFO
        log.log(level, "robot %s: slave %s %s (%s)", self.robot_id, slave.peer_id, change, reason)
        self._peer_changed(slave, change, reason, now)
        event: safety.Event = (
            safety.SlaveLost(slave.peer_id, reason) if lost else safety.SlaveDetach(slave.peer_id)
        )
        self.apply(event, now, cause=reason)

    # -- drivers ------------------------------------------------------------------------------

    async def _run_driver(
        self, peer: Master | Slave, driver: Driver, scope: trio.CancelScope, closed: trio.Event
    ) -> None:
        error: BaseException | None = None
        with scope:
            try:
                await driver.run(peer.link)
            except Exception as exc:  # a failing driver is reported, never fatal to the robot
                error = exc
            finally:
                closed.set()
        if not scope.cancel_called:
            # Through the inbox, like every message: a `command_now` must not overtake it.
            with contextlib.suppress(ArenaError):  # the robot has stopped
                await self._port.post(inbox.DriverEndedMsg(peer, error))
