"""The robot handle: the `Robot` object that everyone else holds.

A `Robot` posts a message to its actor (`arena.robot.actor`) and waits for the answer; it never
changes the robot's state itself. The one exception is the actor's idle turn (`arena.robot.idle`):
while the actor waits on an empty inbox, a command, an e-stop or a heartbeat is decided at once in
the caller's task, as the actor would have decided it next.
"""

from __future__ import annotations

import contextlib
import time as wallclock
from collections.abc import Iterable, Iterator, Mapping
from typing import Any

import trio

from arena.protocol.errors import ArenaError, ErrorCode, Severity
from arena.protocol.rest import DEFAULT_TENANT
from arena.robot import safety
from arena.robot.actor import Actor
from arena.robot.core import RobotCore
from arena.robot.episodes import Episode
from arena.robot.events import Audited, MotionStopped, PolicyInferred, RobotEvent
from arena.robot.idle import IdleTurn
from arena.robot.inbox import (
    AliveMsg,
    AttachMsg,
    CommandMsg,
    DetachMsg,
    EpisodeMsg,
    EventMsg,
    Msg,
    Reply,
    SensorFaultMsg,
    ShutdownMsg,
    WorkspaceMsg,
)
from arena.robot.links import MasterDriver, MasterLink, SlaveDriver, SlaveLink
from arena.robot.mailbox import EventQueue
from arena.robot.model import RobotModel, SafetyPolicy
from arena.robot.motion import Command, CommandResult
from arena.robot.snapshot import JointSnapshot, MasterEnded, RobotSnapshot
from arena.robot.teleop import TeleopSettings
from arena.robot.workspace import Workspace

#: Seconds a hand-back or detach waits for the master's driver to let its hardware go (a bus
#: worker's stop gives up after 5).
CLOSE_PATIENCE = 6.0


class Robot:
    """One robot: its public handle; `run` is its actor's task."""

    def __init__(
        self,
        robot_id: str,
        name: str,
        model: RobotModel,
        policy: SafetyPolicy | None = None,
        inbox_size: int = 1024,
        tenant: str = DEFAULT_TENANT,
    ) -> None:
        self.robot_id = robot_id
        self.name = name
        self.model = model
        #: Whose robot it is (a lab, a class): only callers of that tenant see it, and its
        #: recorded data goes into that tenant's recording files.
        self.tenant = tenant
        self.core = RobotCore(model, trio.current_time(), policy)
        self._send, receive = trio.open_memory_channel[Msg](inbox_size)
        self._turn = IdleTurn()  # the actor's idle turn (`arena.robot.idle`)
        self._actor = Actor(robot_id, self.core, _Port(self), (self._send, receive), self._turn)
        #: Set once the actor has ended.
        self.stopped = self._actor.stopped
        #: Commands answered, by outcome: "accepted" or the refusal code (for metrics).
        self.command_counts = self._actor.command_counts
        #: Data-collection episodes (owned by the actor: changed only through `episode`).
        self.episodes = self._actor.episodes
        #: Teleoperation's box and dead-man time set over REST (None: the default from the
        #: hand and the workspace, `arena.robot.teleop.settings_of`).
        self.teleop: TeleopSettings | None = None

    # -- what the robot is ----------------------------------------------------------------------

    @property
    def estop_count(self) -> int:
        """E-stops the robot went through."""
        return self._actor.estop_count

    @property
    def intervention_count(self) -> int:
        """Interventions (corrections) started on the robot."""
        return self._actor.intervention_count

    @property
    def last_master(self) -> MasterEnded | None:
        """The last master that left the robot, how and why (None: none has)."""
        return self._actor.last_master

    @property
    def last_stop(self) -> MotionStopped | None:
        """The last motion the collision guard stopped on its way (None: none was)."""
        return self._actor.last_stop

    @property
    def targets_superseded(self) -> int:
        """Targets a newer one replaced before a slave took it (latest wins toward a slave
        slower than its master); every accepted command is still recorded."""
        return self._actor.targets_superseded

    @property
    def workspace(self) -> Workspace:
        """Where the arm may go (the collision guard's floor and keep-out boxes)."""
        return self.core.workspace

    def snapshot(self) -> RobotSnapshot:
        """The robot as it is now."""
        state = self.core.state
        virtual = self.core.motion.positions
        goals = self.core.motion.goals
        real = self._actor.real
        joints = tuple(
            JointSnapshot(
                j.name,
                j.servo_id,
                virtual[j.name],
                real.get(j.name),
                goals[j.name],
                j.lower,
                j.upper,
                j.max_velocity,
            )
            for j in self.model.joints
        )
        peers = self._actor.peers
        paused = state.mode is safety.Mode.PAUSED
        master = peers.master.snapshot(paused=paused) if peers.master is not None else None
        waiting = peers.waiting.snapshot(paused=True) if peers.waiting is not None else None
        joining = self.core.joining
        slaves = tuple(p.snapshot(p.peer_id in joining) for p in peers.slaves.values())
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
            waiting,
        )

    def joint_values(self) -> tuple[dict[str, float], Mapping[str, float]]:
        """Virtual (commanded) and real (measured) values now, by joint name, in degrees.

        Much cheaper than `snapshot` (for messages sent with every command). The real values
        are the robot's own mapping: read it at once, never keep or change it.
        """
        return self.core.motion.positions, self._actor.real

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
        self._actor.observers.add(queue, None if kinds is None else frozenset(kinds))
        if self.stopped.is_set():
            queue.close()
        try:
            yield queue
        finally:
            self._actor.observers.remove(queue)

    # -- commands and safety --------------------------------------------------------------------

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
        """Decide `command` in the caller's task, in the actor's idle turn; else None (use
        `command`).

        Idle means blocked on an empty inbox with no timer due: a posted command would be the
        actor's very next step, so deciding it here gives the same answer in the same order,
        without two task switches. The network edge tries this first.
        """
        results = self.command_run_now([command], master_id, burst_goes_on=in_burst)
        return None if results is None else results[0]

    def command_run_now(
        self, commands: list[Command], master_id: str | None = None, *, burst_goes_on: bool = False
    ) -> list[CommandResult] | None:
        """Decide a run of commands sent together, in the caller's task, in the actor's idle
        turn (see `command_now`); else None. Each is decided, recorded and answered on its own
        and in order, all but the last as in a burst (the last too if `burst_goes_on`); what
        they share is the time they are decided at, as they arrived together."""
        turn = self._turn
        now = turn.now()
        if now is None:
            return None
        actor = self._actor
        last = len(commands) - 1
        results = [
            actor.decide(master_id, command, burst_goes_on or k < last, now)
            for k, command in enumerate(commands)
        ]
        turn.wake_at(actor.deadline())
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
        """The e-stop applied in the caller's task in the actor's idle turn (as `command_now`
        decides a command), its slaves told at once; else None (use `estop`)."""
        now = self._turn.now()
        if now is None:
            return None
        event = safety.EStop(reason)
        outcome = self._actor.apply(event, now, cause=type(event).__name__)
        self._turn.wake_at(self._actor.deadline())
        return outcome

    async def reset(self) -> safety.Outcome:
        """Leave the e-stop. Causes no motion by itself."""
        return await self._event(safety.Reset())

    async def pause(self) -> safety.Outcome:
        """Pause the robot's master: it sends nothing and the robot holds where it is."""
        return await self._event(safety.MasterPause())

    async def resume(self) -> safety.Outcome:
        """Resume the paused master."""
        return await self._event(safety.MasterResume())

    async def end_intervention(self, resume: bool = True) -> safety.Outcome:
        """End the intervention: the intervening master goes and the paused master resumes
        (unless `resume` is false: then it stays paused). Returns once a driver the robot ran
        for the intervening master has let its hardware go (a leader arm limp, its port
        closed), at most `CLOSE_PATIENCE` seconds."""
        peers = self._actor.peers
        closed = peers.master.closed if peers.waiting and peers.master else None
        outcome = await self._event(safety.InterventionEnd(resume))
        if closed is not None and not isinstance(outcome, safety.Refused):
            with trio.move_on_after(CLOSE_PATIENCE):
                await closed()
        return outcome

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

    async def highlight(self, task: str, keep: float, since: float) -> Episode:
        """Keep the last `keep` seconds as a kept episode of `task` (none before `since`,
        trio time, nor before the last episode's end), marked in the recording at its own
        times; EPISODE_ACTIVE while an episode runs."""
        reply: Reply[Episode] = Reply()
        await self._post(EpisodeMsg("highlight", task, reply, since, keep))
        return await reply.wait()

    def master_driver(self) -> object | None:
        """The driver of the master this robot runs itself, paused or driving (None: the
        master runs elsewhere or there is none); during an intervention, the paused one's."""
        peers = self._actor.peers
        for peer in (peers.waiting, peers.master):
            if peer is not None and peer.driver is not None:
                return peer.driver
        return None

    def audit(self, user: str, action: str, detail: str = "") -> None:
        """Record who did what (`events.Audited`). It changes nothing in the robot, so it
        goes straight to the observers, in order with what the actor publishes; never
        blocks."""
        self._actor.observers.publish(
            Audited(self.robot_id, user, action, detail, trio.current_time(), wallclock.time())
        )

    def report_inference(self, event: PolicyInferred) -> None:
        """Record one inference of a policy master (`events.PolicyInferred`). Like an audit
        it changes nothing in the robot: straight to the observers; never blocks."""
        self._actor.observers.publish(event)

    def report_sensor_fault(
        self, sensor_id: str, code: str, message: str, severity: Severity
    ) -> None:
        """Report a sensor's fault (a camera that failed or came back). Sensors are not part
        of the safety envelope: the report is seen and recorded, it never stops the robot.
        Never blocks; dropped if the inbox is full."""
        self._post_nowait(SensorFaultMsg(sensor_id, code, message, severity), drop_if_full=True)

    # -- masters and slaves ---------------------------------------------------------------------

    async def attach_master(
        self,
        driver: MasterDriver,
        *,
        takeover: bool | None = None,
        master_id: str | None = None,
        intervene: bool = False,
    ) -> str:
        """Run `driver` as this robot's master; returns its id. Refusals raise `ArenaError`.

        `takeover` defaults to the driver's own `takes_over`; `intervene`: the running master
        is paused, not ended, until the intervention ends (`end_intervention`).
        """
        if takeover is None:
            takeover = driver.takes_over
        description = str(getattr(driver, "description", "") or "")
        link: MasterLink = await self._attach(
            "master",
            master_id,
            driver.kind,
            driver,
            driver.autonomous,
            takeover,
            None,
            description,
            intervene,
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
        intervene: bool = False,
    ) -> MasterLink:
        """Claim the robot for a master that runs elsewhere (a network connection);
        `description` says what it is to a master it takes over from; `intervene`: it
        intervenes (see `attach_master`)."""
        link: MasterLink = await self._attach(
            "master",
            master_id,
            kind,
            None,
            autonomous,
            takeover,
            heartbeat_timeout,
            description,
            intervene,
        )
        return link

    async def detach_master(
        self,
        master_id: str | None = None,
        reason: str = "detached on request",
        *,
        wait_closed: bool = False,
    ) -> None:
        """Detach the master `master_id` (or whichever master holds the robot). With
        `wait_closed`, return once a driver the robot ran for it has let its hardware go (at
        most `CLOSE_PATIENCE` seconds; never from inside that driver: it would wait for
        itself)."""
        master = self._actor.peers.either_named(master_id)
        await self._leave("master", master_id, lost=False, reason=reason)
        if wait_closed and master is not None and master.closed is not None:
            with trio.move_on_after(CLOSE_PATIENCE):
                await master.closed()

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
        """Attach a slave that runs elsewhere (a network connection). Whether it measures is
        not known until it reports: once it has reported every joint it joins as an arm does
        (`RobotCore.slave_attached`); until then it gets the robot's targets as a twin."""
        link: SlaveLink = await self._attach(
            "slave", slave_id, kind, None, False, False, heartbeat_timeout
        )
        return link

    async def detach_slave(self, slave_id: str, reason: str = "detached on request") -> None:
        """Detach a slave; it is told to stop. Unknown ids raise `ArenaError(UNKNOWN_SLAVE)`."""
        await self._leave("slave", slave_id, lost=False, reason=reason)

    def plan_stop(self) -> None:
        """Say that the robot is about to stop as planned (the server's SIGTERM), before
        `shutdown`: each slave that drives hardware leaves it as its own `estop` setting says
        (`hold`: torque on where it is), not limp as a detach leaves it. It changes nothing in
        the robot's state; it never blocks."""
        for slave in self._actor.peers.slaves.values():
            planned_stop = getattr(slave.driver, "planned_stop", None)
            if planned_stop is not None:
                planned_stop()

    # -- the actor ------------------------------------------------------------------------------

    async def run(self, *, task_status: Any = trio.TASK_STATUS_IGNORED) -> None:
        """The actor's loop (`Actor.run`). Runs until `shutdown` (or cancellation)."""
        await self._actor.run(task_status=task_status)

    async def shutdown(self, reason: str = "robot deleted") -> None:
        """Stop every driver cleanly and end the actor."""
        reply: Reply[None] = Reply()
        try:
            await self._post(ShutdownMsg(reason, reply))
            await reply.wait()
        except ArenaError:
            return  # already stopped

    # -- posting --------------------------------------------------------------------------------

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
        intervene: bool = False,
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
                intervene,
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
                        await self._leave(role, peer, lost=False, reason="attach cancelled")
            raise

    async def _leave(
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

    def _alive(self, peer_id: str) -> None:
        now = self._turn.now()
        if now is not None:
            self._actor.peers.touch(peer_id, now)  # only moves a deadline later: no wake_at
        else:
            self._post_nowait(AliveMsg(peer_id), drop_if_full=True)

    async def _event(self, event: safety.Event) -> safety.Outcome:
        reply: Reply[safety.Outcome] = Reply()
        await self._post(EventMsg(event, reply))
        return await reply.wait()

    async def _post(self, message: Msg) -> None:
        self._turn.close()  # the actor has work: nothing may overtake this message
        try:
            await self._send.send(message)
        except (trio.ClosedResourceError, trio.BrokenResourceError):
            raise ArenaError(
                ErrorCode.ROBOT_STOPPED, f"Robot {self.robot_id!r} has stopped."
            ) from None

    def _post_nowait(self, message: Msg, drop_if_full: bool = False) -> None:
        self._turn.close()
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


class _Port:
    """What the robot gives its links (`arena.robot.links.RobotPort`): the handle's ways in,
    as its own bound methods (a command through a link costs no extra call)."""

    __slots__ = ("alive", "command", "command_run_now", "leave", "post", "robot")

    def __init__(self, robot: Robot) -> None:
        self.robot = robot
        self.post = robot._post
        self.alive = robot._alive
        self.leave = robot._leave
        self.command = robot.command
        self.command_run_now = robot.command_run_now
