"""The robot actor: one trio task that owns one robot.

Everything that can change the robot arrives as a message on its bounded inbox and is handled
in order by `Robot.run`. Handling never blocks: decisions come from the pure `RobotCore`, targets
go to per-slave `LatestMailbox`es, events to observers' `EventQueue`s. Master and slave drivers
run in the actor's own nursery, each in a cancel scope: a driver that raises is detached,
reported, and the loss policy applies; nothing else is disturbed.
"""

from __future__ import annotations

import collections
import contextlib
import itertools
import logging
import math
import time as wallclock
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from typing import Any

import trio

from arena.protocol.errors import ArenaError, ErrorCode, Severity
from arena.robot import safety
from arena.robot.core import MANUAL_SOURCE, JoinChange, RobotCore, Step
from arena.robot.episodes import Episode, Episodes
from arena.robot.events import (
    CommandHandled,
    EpisodeChanged,
    FaultReported,
    JointStatesReceived,
    MasterNotice,
    NoticeKind,
    PeerChanged,
    RobotEvent,
    SlaveNotice,
    SlaveTarget,
    StateChanged,
    TakenBy,
    TargetsSent,
)
from arena.robot.inbox import (
    AliveMsg,
    AttachMsg,
    CommandMsg,
    DetachMsg,
    DriverEndedMsg,
    EpisodeMsg,
    EventMsg,
    FaultMsg,
    LinkMsg,
    Msg,
    RejoinMsg,
    Reply,
    SensorFaultMsg,
    ShutdownMsg,
    StatesMsg,
    WorkspaceMsg,
)
from arena.robot.links import MasterDriver, MasterLink, SlaveDriver, SlaveLink
from arena.robot.mailbox import EventQueue
from arena.robot.model import RobotModel, SafetyPolicy
from arena.robot.motion import Command, CommandResult
from arena.robot.snapshot import JointSnapshot, PeerSnapshot, RobotSnapshot
from arena.robot.workspace import Workspace

log = logging.getLogger(__name__)


@dataclass(eq=False)
class _Peer:
    peer_id: str
    role: str
    kind: str
    link: MasterLink | SlaveLink
    scope: trio.CancelScope | None  # set for drivers the robot runs itself
    heartbeat_timeout: float | None
    last_seen: float
    last_error: str | None = None
    real: dict[str, float] = field(default_factory=dict)
    connected: bool = True
    description: str = ""  # what a master is, in words ("sequence 'gentle-wave'")


# ---------------------------------------------------------------------------------------------


class Robot:
    """One robot: its public handle and, in `run`, its actor."""

    def __init__(
        self,
        robot_id: str,
        name: str,
        model: RobotModel,
        policy: SafetyPolicy | None = None,
        inbox_size: int = 1024,
    ) -> None:
        self.robot_id = robot_id
        self.name = name
        self.model = model
        self.core = RobotCore(model, trio.current_time(), policy)
        self._send, self._receive = trio.open_memory_channel[Msg](inbox_size)
        self._master: _Peer | None = None
        self._slaves: dict[str, _Peer] = {}
        # Each observer's queue with the event types it takes (None: every one), and per
        # event type the queues that take it (made on first use, forgotten when one changes).
        self._observers: dict[EventQueue[RobotEvent], frozenset[type] | None] = {}
        self._routes: dict[type, tuple[EventQueue[RobotEvent], ...]] = {}
        self._real: dict[str, float] = {}
        self._ids = itertools.count(1)
        self._next_tick: float | None = None
        self._nursery: trio.Nursery | None = None
        # The actor's wait while it is idle: blocked on an empty inbox, nothing posted since.
        self._idle_wait: trio.CancelScope | None = None
        self.stopped = trio.Event()
        #: Commands answered, by outcome: "accepted" or the refusal code (for metrics).
        self.command_counts: collections.Counter[str] = collections.Counter()
        self.estop_count = 0
        self._superseded_by_gone = 0  # targets superseded at slaves that have left
        #: Data-collection episodes (owned by the actor: changed only through `episode`).
        self.episodes = Episodes()

    # -- public API ---------------------------------------------------------------------------

    @property
    def targets_superseded(self) -> int:
        """Targets a newer one replaced before a slave took it (latest wins toward a slave
        slower than its master); every accepted command is still recorded."""
        current = sum(
            peer.link.mailbox.coalesced
            for peer in self._slaves.values()
            if isinstance(peer.link, SlaveLink)
        )
        return self._superseded_by_gone + current

    async def command(
        self, command: Command, master_id: str | None = None, *, in_burst: bool = False
    ) -> CommandResult:
        """Send a command (from master `master_id`, or manual control if None); `in_burst`:
        more of the master's commands are already in hand (see `RobotCore.command`)."""
        reply: Reply[CommandResult] = Reply()
        await self._post(CommandMsg(master_id, command, reply, in_burst))
        return await reply.wait()

    def command_now(
        self, command: Command, master_id: str | None = None, *, in_burst: bool = False
    ) -> CommandResult | None:
        """Decide `command` in the caller's task, if the actor is idle; else None (use `command`).

        Idle means blocked on an empty inbox with no timer due: a posted command would be the
        actor's very next step, so deciding it here gives the same answer in the same order,
        without two task switches. The network edge tries this first.
        """
        results = self.command_run_now([command], master_id, burst_goes_on=in_burst)
        return None if results is None else results[0]

    def command_run_now(
        self, commands: list[Command], master_id: str | None = None, *, burst_goes_on: bool = False
    ) -> list[CommandResult] | None:
        """Decide a run of commands sent together, in the caller's task, if the actor is idle
        (see `command_now`); else None. Each is decided, recorded and answered on its own and
        in order, all but the last as in a burst (the last too if `burst_goes_on`); what they
        share is the time they are decided at, as they arrived together."""
        now = self._idle_now()
        if now is None:
            return None
        last = len(commands) - 1
        results = [
            self._decide(master_id, command, burst_goes_on or k < last, now)
            for k, command in enumerate(commands)
        ]
        self._rearm_idle_wait()
        return results

    async def estop(self, reason: str = "emergency stop") -> safety.Outcome:
        """Emergency stop: nothing moves until `reset`.

        An idle actor is stopped in the caller's task, before this yields (see `estop_now`).
        """
        outcome = self.estop_now(reason)
        if outcome is None:
            return await self._event(safety.EStop(reason))
        await trio.lowlevel.checkpoint()
        return outcome

    def estop_now(self, reason: str = "emergency stop") -> safety.Outcome | None:
        """The e-stop applied in the caller's task if the actor is idle (as `command_now`
        decides a command), its slaves told at once; else None (use `estop`)."""
        now = self._idle_now()
        if now is None:
            return None
        event = safety.EStop(reason)
        outcome = self._apply(event, now, cause=type(event).__name__)
        self._rearm_idle_wait()
        return outcome

    async def reset(self) -> safety.Outcome:
        """Leave the e-stop. Causes no motion by itself."""
        return await self._event(safety.Reset())

    @property
    def workspace(self) -> Workspace:
        """Where the arm may go (the collision guard's floor and keep-out boxes)."""
        return self.core.workspace

    async def set_workspace(self, workspace: Workspace) -> None:
        """Change where the arm may go, from the next command on."""
        reply: Reply[None] = Reply()
        await self._post(WorkspaceMsg(workspace, reply))
        await reply.wait()

    async def episode(self, action: str, task: str = "") -> Episode:
        """Start, stop or discard a data-collection episode (`episodes.py`); refusals raise
        `ArenaError`."""
        reply: Reply[Episode] = Reply()
        await self._post(EpisodeMsg(action, task, reply))
        return await reply.wait()

    def report_sensor_fault(
        self, sensor_id: str, code: str, message: str, severity: Severity
    ) -> None:
        """Report a sensor's fault (a camera that failed or came back). Sensors are not part
        of the safety envelope: the report is seen and recorded, it never stops the robot.
        Never blocks; dropped if the inbox is full."""
        self._post_nowait(SensorFaultMsg(sensor_id, code, message, severity), drop_if_full=True)

    async def attach_master(
        self, driver: MasterDriver, *, takeover: bool | None = None, master_id: str | None = None
    ) -> str:
        """Run `driver` as this robot's master; returns its id. Refusals raise `ArenaError`.

        `takeover` defaults to the driver's own `takes_over`.
        """
        if takeover is None:
            takeover = driver.takes_over
        description = str(getattr(driver, "description", "") or "")
        link: MasterLink = await self._attach(
            "master", master_id, driver.kind, driver, driver.autonomous, takeover, None, description
        )
        return link.master_id

    async def connect_master(
        self,
        master_id: str | None = None,
        *,
        kind: str = "external",
        takeover: bool = False,
        heartbeat_timeout: float | None = None,
        autonomous: bool = False,
        description: str = "",
    ) -> MasterLink:
        """Claim the robot for a master that runs elsewhere (a network connection);
        `description` says what it is to a master it takes over from."""
        link: MasterLink = await self._attach(
            "master", master_id, kind, None, autonomous, takeover, heartbeat_timeout, description
        )
        return link

    async def detach_master(
        self, master_id: str | None = None, reason: str = "detached on request"
    ) -> None:
        """Detach the master `master_id` (or whichever master holds the robot)."""
        await self._detach("master", master_id, lost=False, reason=reason)

    async def attach_slave(self, driver: SlaveDriver, slave_id: str | None = None) -> str:
        """Run `driver` as a slave of this robot; returns its id. A driver whose `measures`
        is true (the default) joins before it is sent the robot's targets, at its
        `join_speed` if it has one (`RobotCore.slave_attached`)."""
        link: SlaveLink = await self._attach(
            "slave", slave_id, driver.kind, driver, False, False, None
        )
        return link.slave_id

    async def connect_slave(
        self,
        slave_id: str | None = None,
        *,
        kind: str = "external",
        heartbeat_timeout: float | None = None,
    ) -> SlaveLink:
        """Attach a slave that runs elsewhere (a network connection)."""
        link: SlaveLink = await self._attach(
            "slave", slave_id, kind, None, False, False, heartbeat_timeout
        )
        return link

    async def detach_slave(self, slave_id: str, reason: str = "detached on request") -> None:
        """Detach a slave; it is told to stop. Unknown ids raise `ArenaError(UNKNOWN_SLAVE)`."""
        await self._detach("slave", slave_id, lost=False, reason=reason)

    @contextlib.contextmanager
    def subscribe(
        self, maxlen: int = 1024, kinds: Iterable[type[RobotEvent]] | None = None
    ) -> Iterator[EventQueue[RobotEvent]]:
        """Observe this robot's events (only those of the types `kinds`, if given): `with
        robot.subscribe() as events: ...`.

        A slow observer loses its oldest events (counted in `events.dropped`); it never slows
        the robot. The queue ends (`trio.EndOfChannel`) when the robot stops, at once if it
        has stopped already.
        """
        queue: EventQueue[RobotEvent] = EventQueue(maxlen)
        self._observers[queue] = None if kinds is None else frozenset(kinds)
        self._routes.clear()
        if self.stopped.is_set():
            queue.close()
        try:
            yield queue
        finally:
            del self._observers[queue]
            self._routes.clear()
            queue.close()

    def snapshot(self) -> RobotSnapshot:
        """The robot as it is now."""
        state = self.core.state
        virtual = self.core.motion.positions
        goals = self.core.motion.goals
        joints = tuple(
            JointSnapshot(
                j.name,
                j.servo_id,
                virtual[j.name],
                self._real.get(j.name),
                goals[j.name],
                j.lower,
                j.upper,
                j.max_velocity,
            )
            for j in self.model.joints
        )
        master = self._peer_snapshot(self._master) if self._master else None
        joining = self.core.joining
        slaves = tuple(self._peer_snapshot(p, p.peer_id in joining) for p in self._slaves.values())
        return RobotSnapshot(
            self.robot_id,
            self.name,
            self.model.robot_type,
            state.mode,
            state.owner,
            state.estop_reason,
            master,
            slaves,
            joints,
        )

    def joint_values(self) -> tuple[dict[str, float], Mapping[str, float]]:
        """Virtual (commanded) and real (measured) values now, by joint name, in degrees.

        Much cheaper than `snapshot` (for messages sent with every command). The real values
        are the robot's own mapping: read it at once, never keep or change it.
        """
        return self.core.motion.positions, self._real

    async def shutdown(self, reason: str = "robot deleted") -> None:
        """Stop every driver cleanly and end the actor."""
        reply: Reply[None] = Reply()
        try:
            await self._post(ShutdownMsg(reason, reply))
            await reply.wait()
        except ArenaError:
            return  # already stopped

    # -- the actor ----------------------------------------------------------------------------

    async def run(self, *, task_status: Any = trio.TASK_STATUS_IGNORED) -> None:
        """The actor loop. Runs until `shutdown` (or cancellation)."""
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
            for queue in list(self._observers):
                queue.close()
            self.stopped.set()

    async def _loop(self) -> None:
        while True:
            deadline = self._next_deadline()
            message: Msg | None = None
            with trio.move_on_at(deadline) as wait:
                if not self._receive.statistics().current_buffer_used:
                    self._idle_wait = wait
                try:
                    message = await self._receive.receive()
                finally:
                    self._idle_wait = None
            now = trio.current_time()
            if message is None:
                self._on_timers(now)
                continue
            if isinstance(message, ShutdownMsg):
                self._on_shutdown(message.reason)
                if message.reply is not None:
                    message.reply.set(None)
                return
            self._dispatch(message, now)

    def _next_deadline(self) -> float:
        deadline = self._next_tick if self._next_tick is not None else math.inf
        for peer in self._peers():
            if peer.heartbeat_timeout is not None:
                deadline = min(deadline, peer.last_seen + peer.heartbeat_timeout)
        return deadline

    def _peers(self) -> list[_Peer]:
        peers = list(self._slaves.values())
        if self._master is not None:
            peers.append(self._master)
        return peers

    def _dispatch(self, message: Msg, now: float) -> None:
        if isinstance(message, CommandMsg):
            self._on_command(message, now)
        elif isinstance(message, StatesMsg):
            self._on_states(message, now)
        elif isinstance(message, EventMsg):
            outcome = self._apply(message.event, now, cause=type(message.event).__name__)
            if message.reply is not None:
                message.reply.set(outcome)
        elif isinstance(message, AttachMsg):
            self._on_attach(message, now)
        elif isinstance(message, DetachMsg):
            self._on_detach(message, now)
        elif isinstance(message, FaultMsg):
            self._on_fault(message, now)
        elif isinstance(message, AliveMsg):
            self._touch(message.peer_id, now)
        elif isinstance(message, LinkMsg):
            self._on_link(message, now)
        elif isinstance(message, RejoinMsg):
            self._on_rejoin(message, now)
        elif isinstance(message, DriverEndedMsg):
            self._on_driver_ended(message, now)
        elif isinstance(message, WorkspaceMsg):
            self.core.workspace = message.workspace  # checked from the next command on
            message.reply.set(None)
        elif isinstance(message, EpisodeMsg):
            self._on_episode(message, now)
        elif isinstance(message, SensorFaultMsg):
            self._publish(
                FaultReported(
                    self.robot_id,
                    message.sensor_id,
                    message.code,
                    message.message,
                    message.severity,
                    None,
                    now,
                    wallclock.time(),
                )
            )

    # -- handlers -----------------------------------------------------------------------------

    def _idle_now(self) -> float | None:
        """The time, if the actor is idle and no timer is due; else None."""
        wait = self._idle_wait
        if wait is None:
            return None
        now = trio.current_time()
        return now if now < wait.deadline else None

    def _rearm_idle_wait(self) -> None:
        """After a command decided outside the actor: wake it for a motion tick now sooner.

        (A command can only bring the next tick closer; heartbeat deadlines only move later.)
        """
        wait, tick = self._idle_wait, self._next_tick
        if wait is not None and tick is not None and tick < wait.deadline:
            wait.deadline = tick

    def _alive(self, peer_id: str) -> None:
        now = self._idle_now()
        if now is not None:
            self._touch(peer_id, now)  # only moves a deadline later: no rearm needed
        else:
            self._post_nowait(AliveMsg(peer_id), drop_if_full=True)

    def _on_command(self, message: CommandMsg, now: float) -> None:
        result = self._decide(message.source, message.command, message.in_burst, now)
        if message.reply is not None:
            message.reply.set(result)

    def _decide(
        self, source: str | None, command: Command, in_burst: bool, now: float
    ) -> CommandResult:
        """A command decided, counted, published and its targets sent."""
        if source is not None:
            self._touch(source, now)
        result, step = self.core.command(source, command, now, in_burst=in_burst)
        self.command_counts["accepted" if result.accepted else str(result.code)] += 1
        self._publish(
            CommandHandled(
                self.robot_id, source or MANUAL_SOURCE, command, result, now, wallclock.time()
            )
        )
        self._send_targets(step.targets, now, more_follow=in_burst)
        if step.joins:
            self._carry_out_joins(step.joins, now)
        return result

    def _on_states(self, message: StatesMsg, now: float) -> None:
        peer = self._slaves.get(message.slave_id)
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
        self._real.update(joints)
        self._publish(
            JointStatesReceived(self.robot_id, message.slave_id, joints, now, wallclock.time())
        )
        if message.slave_id in self.core.joining:
            self._carry_out_joins(self.core.slave_measured(message.slave_id, joints, now), now)

    def _on_fault(self, message: FaultMsg, now: float) -> None:
        peer = self._slaves.get(message.peer_id)
        if peer is None:
            return
        peer.last_seen = now
        peer.last_error = f"{message.code}: {message.message}"
        joint = self.model.joint(message.joint) if message.joint else None
        self._publish(
            FaultReported(
                self.robot_id,
                message.peer_id,
                message.code,
                message.message,
                message.severity,
                joint.name if joint else message.joint,
                now,
                wallclock.time(),
            )
        )
        self._apply(
            safety.SlaveError(message.peer_id, message.severity, message.message),
            now,
            cause=message.code,
        )

    def _on_episode(self, message: EpisodeMsg, now: float) -> None:
        try:
            if message.action == "start":
                episode = self.episodes.start(message.task, now)
            elif message.action == "stop":
                episode = self.episodes.stop(now)
            else:
                episode = self.episodes.discard(now)
        except ArenaError as refusal:
            message.reply.fail(refusal)
            return
        self._publish(
            EpisodeChanged(
                self.robot_id,
                message.action,
                episode.index,
                episode.task,
                episode.started,
                now,
                wallclock.time(),
            )
        )
        message.reply.set(episode)

    def _on_link(self, message: LinkMsg, now: float) -> None:
        peer = self._slaves.get(message.slave_id)
        if peer is None or peer.connected == message.connected:
            return
        peer.connected = message.connected
        change = "reconnected" if message.connected else "disconnected"
        log.log(
            logging.INFO if message.connected else logging.WARNING,
            "robot %s: slave %s %s (%s)",
            self.robot_id,
            peer.peer_id,
            change,
            message.reason,
        )
        self._publish(
            PeerChanged(
                self.robot_id,
                "slave",
                peer.peer_id,
                peer.kind,
                change,
                message.reason,
                now,
                wallclock.time(),
            )
        )
        if not message.connected:
            peer.last_error = f"{ErrorCode.SLAVE_LOST}: {message.reason}"
            self._apply(safety.SlaveLost(peer.peer_id, message.reason), now, cause=message.reason)
        else:
            self.core.slave_rejoins(peer.peer_id)  # its arm may have been moved meanwhile

    def _on_rejoin(self, message: RejoinMsg, now: float) -> None:
        peer = self._slaves.get(message.slave_id)
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

    def _on_attach(self, message: AttachMsg, now: float) -> None:
        peer_id = message.peer_id or f"{message.role}-{next(self._ids)}"
        link: MasterLink | SlaveLink
        if message.role == "master":
            link = MasterLink(self, peer_id)
            outcome = self._apply(
                safety.MasterAttach(
                    peer_id,
                    message.autonomous,
                    message.takeover,
                    message.kind,
                    message.description,
                ),
                now,
                cause="master attach",
            )
            if isinstance(outcome, safety.Refused):
                log.info("robot %s: master %s refused (%s)", self.robot_id, peer_id, outcome.code)
                self._publish(
                    PeerChanged(
                        self.robot_id,
                        "master",
                        peer_id,
                        message.kind,
                        "refused",
                        outcome.message,
                        now,
                        wallclock.time(),
                    )
                )
                message.reply.fail(ArenaError(outcome.code, outcome.message))
                return
        else:
            if peer_id in self._slaves:
                message.reply.fail(
                    ArenaError(
                        ErrorCode.INVALID_CONFIG, f"A slave called {peer_id!r} is attached already."
                    )
                )
                return
            link = SlaveLink(self, peer_id)
            self._apply(safety.SlaveAttach(peer_id), now, cause="slave attach")
            driver = message.driver
            self.core.slave_attached(
                peer_id,
                measures=driver is not None and getattr(driver, "measures", True),
                join_speed=getattr(driver, "join_speed", None),
            )
        scope = trio.CancelScope() if message.driver is not None else None
        peer = _Peer(
            peer_id, message.role, message.kind, link, scope, message.heartbeat_timeout, now
        )
        peer.description = message.description
        if message.role == "master":
            self._master = peer
        else:
            self._slaves[peer_id] = peer
        if message.driver is not None:
            assert self._nursery is not None
            self._nursery.start_soon(self._run_driver, peer, message.driver)
        log.info(
            "robot %s: %s %s attached (%s)", self.robot_id, message.role, peer_id, message.kind
        )
        self._publish(
            PeerChanged(
                self.robot_id,
                message.role,
                peer_id,
                message.kind,
                "attached",
                "",
                now,
                wallclock.time(),
                message.autonomous,
            )
        )
        message.reply.set(link)

    def _on_detach(self, message: DetachMsg, now: float) -> None:
        if message.role == "master":
            peer = self._master
            if peer is None or (message.peer_id is not None and peer.peer_id != message.peer_id):
                if message.reply is not None:
                    message.reply.set(None)  # not the master (any more): nothing to do
                return
            event: safety.Event = (
                safety.MasterLost(peer.peer_id, message.reason)
                if message.lost
                else safety.MasterDetach(peer.peer_id, message.hold)
            )
            self._apply(event, now, cause=message.reason)
            change = "lost" if message.lost else "released" if message.released else "detached"
            self._drop_master(
                peer, ErrorCode.MASTER_LOST if message.lost else None, message.reason, change, now
            )
        else:
            slave = self._slaves.get(message.peer_id or "")
            if slave is None:
                if message.reply is not None:
                    message.reply.fail(
                        ArenaError(
                            ErrorCode.UNKNOWN_SLAVE, f"No slave {message.peer_id!r} on this robot."
                        )
                    )
                return
            self._drop_slave(slave, message.reason, lost=message.lost, now=now)
        if message.reply is not None:
            message.reply.set(None)

    def _on_driver_ended(self, message: DriverEndedMsg, now: float) -> None:
        peer = message.peer
        if peer is not self._master and self._slaves.get(peer.peer_id) is not peer:
            return  # already detached by the robot
        error = message.error
        if error is not None:
            text = f"{type(error).__name__}: {error}"
            log.error(
                "robot %s: %s driver %s failed: %s",
                self.robot_id,
                peer.role,
                peer.peer_id,
                text,
                exc_info=error,
            )
            self._publish(
                FaultReported(
                    self.robot_id,
                    peer.peer_id,
                    ErrorCode.DRIVER_FAILED,
                    text,
                    Severity.ERROR,
                    None,
                    now,
                    wallclock.time(),
                )
            )
        if peer.role == "master":
            reason = "driver failed" if error else "driver finished"
            event: safety.Event = (
                safety.MasterLost(peer.peer_id, reason)
                if error
                else safety.MasterDetach(peer.peer_id, hold=False)  # its last move completes
            )
            self._apply(event, now, cause=reason)
            self._drop_master(
                peer,
                ErrorCode.DRIVER_FAILED if error else None,
                reason,
                "lost" if error else "detached",
                now,
            )
        else:
            self._drop_slave(
                peer,
                "driver failed" if error else "driver finished",
                lost=error is not None,
                now=now,
            )

    def _on_timers(self, now: float) -> None:
        if self._next_tick is not None and now >= self._next_tick:
            self._next_tick = None
            self._send_targets(self.core.tick(now), now)
            self._carry_out_joins(self.core.advance_joins(now), now)
        for peer in self._peers():
            timeout = peer.heartbeat_timeout
            if timeout is not None and now >= peer.last_seen + timeout:
                log.warning(
                    "robot %s: %s %s missed its heartbeat", self.robot_id, peer.role, peer.peer_id
                )
                if peer.role == "master":
                    self._apply(
                        safety.HeartbeatTimeout(peer.peer_id), now, cause="heartbeat timeout"
                    )
                    if self._master is peer:
                        self._drop_master(
                            peer, ErrorCode.MASTER_LOST, "heartbeat timeout", "lost", now
                        )
                else:
                    self._drop_slave(peer, "heartbeat timeout", lost=True, now=now)

    def _on_shutdown(self, reason: str) -> None:
        now = trio.current_time()
        if self._master is not None:
            self._apply(safety.MasterDetach(self._master.peer_id), now, cause=reason)
            self._drop_master(self._master, ErrorCode.ROBOT_STOPPED, reason, "detached", now)
        for slave in list(self._slaves.values()):
            self._drop_slave(slave, reason, lost=False, now=now)
        log.info("robot %s: stopped (%s)", self.robot_id, reason)

    # -- effects ------------------------------------------------------------------------------

    def _apply(self, event: safety.Event, now: float, cause: str) -> safety.Outcome:
        before = self.core.state
        step = self.core.handle(event, now)
        self._carry_out(step, now)
        after = self.core.state
        if (before.mode, before.owner, before.estop_reason) != (
            after.mode,
            after.owner,
            after.estop_reason,
        ):
            self._state_changed(cause, now)
        return step.outcome

    def _carry_out(self, step: Step, now: float) -> None:
        self._send_targets(step.targets, now)
        self._carry_out_joins(step.joins, now)
        for effect in step.effects:
            if isinstance(effect, safety.DetachMaster):
                if self._master is not None and self._master.peer_id == effect.master_id:
                    by = effect.by
                    self._drop_master(
                        self._master,
                        effect.code,
                        effect.message,
                        "detached",
                        now,
                        None if by is None else TakenBy(by.master_id, by.kind, by.description),
                    )
            elif isinstance(effect, safety.StopMotion):
                self.estop_count += 1
                log.warning("robot %s: e-stop (%s)", self.robot_id, effect.reason)
                self._notify_slaves(SlaveNotice(NoticeKind.ESTOP, effect.reason), clears=True)
            elif isinstance(effect, safety.HoldPosition):
                self._notify_slaves(SlaveNotice(NoticeKind.HOLD, "holding position"))
            elif isinstance(effect, safety.ResumeSlaves):
                log.info("robot %s: reset", self.robot_id)
                self._notify_slaves(SlaveNotice(NoticeKind.RESET, "e-stop reset"))
        if self._next_tick is None:
            self._next_tick = self.core.next_tick(now)

    def _send_targets(
        self, targets: dict[str, float] | None, now: float, *, more_follow: bool = False
    ) -> None:
        if targets is not None:
            target = SlaveTarget(targets, now, more_follow)
            joining = self.core.joining  # they get targets of their own (`_carry_out_joins`)
            for slave in self._slaves.values():
                assert isinstance(slave.link, SlaveLink)
                if not joining or slave.peer_id not in joining:
                    slave.link.mailbox.put_target(target)
            self._publish(TargetsSent(self.robot_id, targets, now, wallclock.time()))
        if self._next_tick is None:
            self._next_tick = self.core.next_tick(now)

    def _carry_out_joins(self, changes: Iterable[JoinChange], now: float) -> None:
        """Send joining slaves their own targets, the robot's an adopted pose; report each
        change of a join as a `PeerChanged` (recorded)."""
        for change in changes:
            if change.robot_targets is not None:
                self._send_targets(change.robot_targets, now)
            peer = self._slaves.get(change.slave_id)
            if peer is None:
                continue
            assert isinstance(peer.link, SlaveLink)
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
                self._publish(
                    PeerChanged(
                        self.robot_id,
                        "slave",
                        peer.peer_id,
                        peer.kind,
                        change.change,
                        change.reason,
                        now,
                        wallclock.time(),
                    )
                )
        if self._next_tick is None:
            self._next_tick = self.core.next_tick(now)

    def _notify_slaves(self, notice: SlaveNotice, clears: bool = False) -> None:
        for slave in self._slaves.values():
            assert isinstance(slave.link, SlaveLink)
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
        if self._master is not None:
            assert isinstance(self._master.link, MasterLink)
            self._master.link.notices.put(MasterNotice("state", None, cause, state.mode))

    def _drop_master(
        self,
        peer: _Peer,
        code: ErrorCode | None,
        reason: str,
        change: str,
        now: float,
        by: TakenBy | None = None,
    ) -> None:
        if self._master is not peer:
            return
        self._master = None
        self.core.forget_master(peer.peer_id)
        assert isinstance(peer.link, MasterLink)
        if code is not None:
            peer.link.notices.put(MasterNotice("detached", code, reason, by=by))
        peer.link.detached.set()
        peer.link.notices.close()
        if peer.scope is not None:
            peer.scope.cancel()
        log.info("robot %s: master %s %s (%s)", self.robot_id, peer.peer_id, change, reason)
        self._publish(
            PeerChanged(
                self.robot_id,
                "master",
                peer.peer_id,
                peer.kind,
                change,
                reason,
                now,
                wallclock.time(),
            )
        )

    def _drop_slave(self, peer: _Peer, reason: str, *, lost: bool, now: float) -> None:
        if self._slaves.get(peer.peer_id) is not peer:
            return
        del self._slaves[peer.peer_id]
        self.core.slave_detached(peer.peer_id)
        assert isinstance(peer.link, SlaveLink)
        self._superseded_by_gone += peer.link.mailbox.coalesced
        assert isinstance(peer.link, SlaveLink)
        peer.link.mailbox.put_notice(SlaveNotice(NoticeKind.SHUTDOWN, reason), clears=True)
        peer.link.mailbox.close()
        if peer.scope is not None:
            peer.scope.cancel()
        event: safety.Event = (
            safety.SlaveLost(peer.peer_id, reason) if lost else safety.SlaveDetach(peer.peer_id)
        )
        log.log(
            logging.WARNING if lost else logging.INFO,
            "robot %s: slave %s %s (%s)",
            self.robot_id,
            peer.peer_id,
            "lost" if lost else "detached",
            reason,
        )
        self._publish(
            PeerChanged(
                self.robot_id,
                "slave",
                peer.peer_id,
                peer.kind,
                "lost" if lost else "detached",
                reason,
                now,
                wallclock.time(),
            )
        )
        self._apply(event, now, cause=reason)

    def _touch(self, peer_id: str, now: float) -> None:
        if self._master is not None and self._master.peer_id == peer_id:
            self._master.last_seen = now
        elif (slave := self._slaves.get(peer_id)) is not None:
            slave.last_seen = now

    def _publish(self, event: RobotEvent) -> None:
        queues = self._routes.get(type(event))
        if queues is None:
            kind = type(event)
            queues = self._routes[kind] = tuple(
                queue for queue, kinds in self._observers.items() if kinds is None or kind in kinds
            )
        for queue in queues:
            queue.put(event)

    # -- plumbing -----------------------------------------------------------------------------

    async def _run_driver(self, peer: _Peer, driver: MasterDriver | SlaveDriver) -> None:
        assert peer.scope is not None
        error: BaseException | None = None
        with peer.scope:
            try:
                await driver.run(peer.link)  # type: ignore[arg-type]
            except Exception as exc:  # a failing driver is reported, never fatal to the robot
                error = exc
        if not peer.scope.cancel_called:
            # Through `_post`, like every message: a `command_now` must not overtake it.
            with contextlib.suppress(ArenaError):  # the robot has stopped
                await self._post(DriverEndedMsg(peer, error))

    async def _attach(
        self,
        role: str,
        peer_id: str | None,
        kind: str,
        driver: MasterDriver | SlaveDriver | None,
        autonomous: bool,
        takeover: bool,
        heartbeat_timeout: float | None,
        description: str = "",
    ) -> Any:
        reply: Reply[Any] = Reply()
        await self._post(
            AttachMsg(
                role,
                peer_id,
                kind,
                driver,
                autonomous,
                takeover,
                heartbeat_timeout,
                reply,
                description,
            )
        )
        try:
            return await reply.wait()
        except trio.Cancelled:
            # The actor attaches the peer all the same: take its answer (it comes at once) and
            # undo it, or the robot would keep a peer that nobody drives (a client that hung up
            # during its handshake, found by the 1,000-connections test).
            with trio.CancelScope(shield=True), trio.move_on_after(5):
                try:
                    link = await reply.wait()
                except ArenaError:
                    pass  # refused: nothing to undo
                else:
                    peer = link.master_id if isinstance(link, MasterLink) else link.slave_id
                    with contextlib.suppress(ArenaError):  # gone already
                        await self._detach(role, peer, lost=False, reason="attach cancelled")
            raise

    async def _detach(
        self,
        role: str,
        peer_id: str | None,
        *,
        lost: bool,
        reason: str,
        hold: bool = True,
        released: bool = False,
    ) -> None:
        reply: Reply[None] = Reply()
        try:
            await self._post(DetachMsg(role, peer_id, lost, reason, reply, hold, released))
            await reply.wait()
        except ArenaError as exc:
            if exc.code is not ErrorCode.ROBOT_STOPPED:
                raise  # else the robot is gone, and the peer with it

    async def _event(self, event: safety.Event) -> safety.Outcome:
        reply: Reply[safety.Outcome] = Reply()
        await self._post(EventMsg(event, reply))
        return await reply.wait()

    async def _post(self, message: Msg) -> None:
        self._idle_wait = None  # the actor has work: nothing may overtake this message
        try:
            await self._send.send(message)
        except (trio.ClosedResourceError, trio.BrokenResourceError):
            raise ArenaError(
                ErrorCode.ROBOT_STOPPED, f"Robot {self.robot_id!r} has stopped."
            ) from None

    def _post_nowait(self, message: Msg, drop_if_full: bool = False) -> None:
        self._idle_wait = None
        try:
            self._send.send_nowait(message)
        except trio.WouldBlock:
            if not drop_if_full:
                raise ArenaError(
                    ErrorCode.OVERLOADED, f"Robot {self.robot_id!r} is overloaded; slow down."
                ) from None
        except (trio.ClosedResourceError, trio.BrokenResourceError):
            raise ArenaError(
                ErrorCode.ROBOT_STOPPED, f"Robot {self.robot_id!r} has stopped."
            ) from None

    def _stop_taking_messages(self) -> None:
        self._idle_wait = None
        self._send.close()
        self._fail_pending(
            ArenaError(ErrorCode.ROBOT_STOPPED, f"Robot {self.robot_id!r} has stopped.")
        )

    def _fail_pending(self, error: ArenaError) -> None:
        while True:
            try:
                message = self._receive.receive_nowait()
            except (trio.WouldBlock, trio.EndOfChannel, trio.ClosedResourceError):
                return
            reply = getattr(message, "reply", None)
            if reply is not None:
                reply.fail(error)

    @staticmethod
    def _peer_snapshot(peer: _Peer, joining: bool = False) -> PeerSnapshot:
        return PeerSnapshot(
            peer.peer_id,
            peer.role,
            peer.kind,
            peer.connected,
            peer.last_error,
            joining,
            peer.description,
        )
