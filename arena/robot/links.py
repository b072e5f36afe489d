"""How drivers and connections meet a robot: the driver protocols, and the links a master or
a slave holds (commands in, notices out; targets out, joint states and faults in).

A link sees its robot through two narrow interfaces, both met by `arena.robot.handle.Robot`:
`RobotView`, what a driver may use of the robot (`link.robot`), and `RobotPort`, the ways in that
the link itself uses (post a message, a heartbeat, leave). It knows nothing else of the robot.
"""

from __future__ import annotations

from collections.abc import AsyncIterator, Iterable, Mapping
from contextlib import AbstractContextManager
from typing import Protocol

import trio

from arena.protocol.errors import ErrorCode, Severity
from arena.robot import safety
from arena.robot.episodes import Episode
from arena.robot.events import (
    MasterNotice,
    NoticeKind,
    PolicyInferred,
    RobotEvent,
    SlaveNotice,
    SlaveTarget,
)
from arena.robot.inbox import (
    FaultMsg,
    LinkMsg,
    Msg,
    RejoinMsg,
    StatesMsg,
)
from arena.robot.mailbox import EventQueue, LatestMailbox
from arena.robot.model import RobotModel
from arena.robot.motion import Command, CommandResult
from arena.robot.snapshot import RobotSnapshot


class RobotView(Protocol):
    """The robot as a link's driver sees it (`link.robot`)."""

    robot_id: str
    model: RobotModel

    def snapshot(self) -> RobotSnapshot:
        """The robot as it is now."""

    def subscribe(
        self, maxlen: int = 1024, kinds: Iterable[type[RobotEvent]] | None = None
    ) -> AbstractContextManager[EventQueue[RobotEvent]]:
        """Observe the robot's events."""

    async def estop(self, reason: str = "emergency stop") -> safety.Outcome:
        """Emergency stop."""

    def estop_now(self, reason: str = "emergency stop") -> safety.Outcome | None:
        """The e-stop applied at once if the robot is idle, else None."""

    async def reset(self) -> safety.Outcome:
        """Leave the e-stop."""

    def report_sensor_fault(
        self, sensor_id: str, code: str, message: str, severity: Severity
    ) -> None:
        """Report a fault of something that is not a slave (a camera, a policy): seen and
        recorded, it never stops the robot."""

    def report_inference(self, event: PolicyInferred) -> None:
        """Record one inference of a policy master."""

    async def episode(self, action: str, task: str = "") -> Episode:
        """Start, stop or discard a data-collection episode."""

    async def highlight(self, task: str, keep: float, since: float) -> Episode:
        """Keep the last `keep` seconds (none before `since`) as an episode of `task`."""


class RobotPort(Protocol):
    """The ways into the robot that a link uses, given to it by the robot."""

    @property
    def robot(self) -> RobotView:
        """The robot, for the link's driver."""

    async def post(self, message: Msg) -> None:
        """Queue `message` on the actor's inbox (`ArenaError(ROBOT_STOPPED)` once stopped)."""

    def alive(self, peer_id: str) -> None:
        """A heartbeat of `peer_id`."""

    async def leave(
        self,
        role: str,
        peer_id: str,
        *,
        lost: bool,
        reason: str,
        hold: bool = True,
        released: bool = False,
    ) -> None:
        """Detach the peer (see `arena.robot.inbox.DetachMsg`)."""

    async def command(
        self, command: Command, master_id: str | None = None, *, in_burst: bool = False
    ) -> CommandResult:
        """A command decided by the actor, in turn."""

    def command_run_now(
        self, commands: list[Command], master_id: str | None = None, *, burst_goes_on: bool = False
    ) -> list[CommandResult] | None:
        """Commands decided at once if the actor is idle, else None."""


class MasterDriver(Protocol):
    """A command source run by the robot (a sequence player, a replay, a remote link).

    It may also have a `description` (what it is in words, "sequence 'gentle-wave'"), which
    a master it takes over from is told.
    """

    kind: str
    autonomous: bool  # plays a program: ends for good on e-stop
    takes_over: bool  # attaching displaces the current master

    async def run(self, link: MasterLink) -> None:
        """Issue commands through `link` until done; returning detaches the master."""


class SlaveDriver(Protocol):
    """An executor run by the robot (a simulated arm, a servo bus, a remote robot)."""

    kind: str

    async def run(self, link: SlaveLink) -> None:
        """Take targets and notices from `link`, report joint states back."""


class MasterLink:
    """A master's handle on the robot: send commands, read notices, leave.

    The robot knows its master by id, and a later connection may take over under the same
    id: once detached, a link speaks for no one (its commands are refused, its heartbeats and
    its leaving change nothing).
    """

    def __init__(self, port: RobotPort, master_id: str) -> None:
        self.robot = port.robot
        self._port = port
        self.master_id = master_id
        self.notices: EventQueue[MasterNotice] = EventQueue(256)
        self.detached = trio.Event()
        #: The robot paused this master (`POST .../master/pause`, an intervention): it must
        #: send nothing until resumed (what it sends is refused `MASTER_PAUSED`).
        self.paused = False
        #: Pauses so far: a driver compares it to tell that a pause came meanwhile.
        self.pauses = 0
        #: Motions of this master's the collision guard stopped on their way (a driver
        #: compares it to tell that a move it waits for will not arrive).
        self.stops = 0
        self.last_stop = ""  # the newest such stop's sentence
        self._resumed = trio.Event()
        self._resumed.set()
        self._paused_at = 0.0
        self._paused_before = 0.0  # seconds paused, pauses that are over

    def set_paused(self, paused: bool, now: float) -> None:
        """The robot pauses or resumes this master (the actor calls this; `now`: trio time)."""
        if paused == self.paused:
            return
        self.paused = paused
        if paused:
            self.pauses += 1
            self._paused_at = now
            self._resumed = trio.Event()
        else:
            self._paused_before += now - self._paused_at
            self._resumed.set()
        self.notices.put(MasterNotice("paused" if paused else "resumed"))

    def paused_time(self, now: float) -> float:
        """Seconds this master was paused so far (a program's clock stands still meanwhile)."""
        current = now - self._paused_at if self.paused else 0.0
        return self._paused_before + current

    async def wait_resumed(self) -> None:
        """Return once the master is not paused (at once if it is not)."""
        await self._resumed.wait()

    async def sleep_until(self, due: float) -> None:
        """Sleep until `due` (trio time) on this master's own clock, which stands still while
        it is paused: a program resumed goes on where it stood (at once when `due` has passed
        and it is not paused, without a checkpoint)."""
        while True:
            if self.paused:
                await self._resumed.wait()
                continue
            target = due + self._paused_before
            if trio.current_time() >= target:
                return
            await trio.sleep_until(target)

    async def command(self, command: Command, *, in_burst: bool = False) -> CommandResult:
        """Send a command as this master and wait for the answer (`in_burst`: more of this
        master's commands are in hand, see `RobotCore.command`)."""
        if self.detached.is_set():
            return DETACHED_LINK
        return await self._port.command(command, master_id=self.master_id, in_burst=in_burst)

    def command_now(self, command: Command, *, in_burst: bool = False) -> CommandResult | None:
        """The answer at once when the robot is idle (see `Robot.command_now`), else None."""
        results = self.command_run_now([command], burst_goes_on=in_burst)
        return None if results is None else results[0]

    def command_run_now(
        self, commands: list[Command], *, burst_goes_on: bool = False
    ) -> list[CommandResult] | None:
        """A run of commands decided at once when the robot is idle (see
        `Robot.command_run_now`), else None."""
        if self.detached.is_set():
            return [DETACHED_LINK] * len(commands)
        return self._port.command_run_now(
            commands, master_id=self.master_id, burst_goes_on=burst_goes_on
        )

    def alive(self) -> None:
        """Heartbeat: the peer is still there."""
        if not self.detached.is_set():
            self._port.alive(self.master_id)

    async def report_fault(
        self, code: str, message: str, severity: Severity = Severity.ERROR, joint: str | None = None
    ) -> None:
        """A fault of this master (a leader arm's servo, say): shown on it, sent to viewers and
        recorded until `clear_fault`; a master's fault never stops the robot by itself."""
        if not self.detached.is_set():
            await self._port.post(
                FaultMsg("master", self.master_id, code, message, severity, joint)
            )

    async def clear_fault(self, code: str, joint: str | None = None, message: str = "") -> None:
        """The fault `code` (at `joint`) is over (`message`: how)."""
        if not self.detached.is_set():
            await self._port.post(
                FaultMsg("master", self.master_id, code, message, Severity.INFO, joint, True)
            )

    async def detach(self, reason: str = "master left", *, finish_motion: bool = False) -> None:
        """Give up ownership; motion in progress stops, unless `finish_motion`."""
        if not self.detached.is_set():
            await self._port.leave(
                "master", self.master_id, lost=False, reason=reason, hold=not finish_motion
            )

    async def release(self, reason: str | None = None, *, hold: bool = False) -> None:
        """The master is done: hand the robot back (no e-stop). The commands it had accepted
        complete (an accepted command is a promise), unless `hold`: then the arm stops where
        it is. `reason` defaults to `RELEASED` or `RELEASED_HOLDING`, which a replay reads."""
        if reason is None:
            reason = RELEASED_HOLDING if hold else RELEASED
        if not self.detached.is_set():
            await self._port.leave(
                "master", self.master_id, lost=False, reason=reason, hold=hold, released=True
            )

    async def lost(self, reason: str = "connection lost") -> None:
        """Report that this master's connection is gone (the loss policy applies)."""
        if not self.detached.is_set():
            await self._port.leave("master", self.master_id, lost=True, reason=reason)


#: Why a master let go, as its release records it: the moves it had accepted complete...
RELEASED = "released by the master"
#: ...or, asked with `hold`, the arm stops where it is.
RELEASED_HOLDING = "released by the master, stopped where it was"

DETACHED_LINK = CommandResult.refused(
    ErrorCode.NOT_OWNER, "This connection no longer holds the robot (it was detached)."
)


class SlaveLink:
    """A slave's handle on the robot: take targets and notices, report states and faults."""

    def __init__(self, port: RobotPort, slave_id: str) -> None:
        self.robot = port.robot
        self._port = port
        self.slave_id = slave_id
        self.mailbox: LatestMailbox[SlaveTarget, SlaveNotice] = LatestMailbox()

    async def receive(self) -> SlaveTarget | SlaveNotice:
        """The next notice, or else the newest target. `trio.EndOfChannel` once detached."""
        return await self.mailbox.get()

    async def messages(self) -> AsyncIterator[SlaveTarget | SlaveNotice]:
        """Every notice and newest target until the slave is detached.

        A shutdown notice is the last thing yielded: the loop ends after it (or when the robot
        goes away), so a driver's `async for` needs no exit of its own.
        """
        while True:
            try:
                message = await self.mailbox.get()
            except trio.EndOfChannel:
                return
            yield message
            if isinstance(message, SlaveNotice) and message.kind is NoticeKind.SHUTDOWN:
                return

    async def report_joint_states(self, joints: Mapping[str, float]) -> None:
        """Real joint values in degrees (protocol names or aliases)."""
        await self._port.post(StatesMsg(self.slave_id, dict(joints)))

    async def report_fault(
        self, code: str, message: str, severity: Severity = Severity.ERROR, joint: str | None = None
    ) -> None:
        """A fault, shown on this slave, sent to viewers and recorded until `clear_fault` (or
        a reset); at or above the robot's e-stop severity it e-stops the robot."""
        await self._port.post(FaultMsg("slave", self.slave_id, code, message, severity, joint))

    async def clear_fault(self, code: str, joint: str | None = None, message: str = "") -> None:
        """The fault `code` (at `joint`) is over (`message`: how)."""
        await self._port.post(
            FaultMsg("slave", self.slave_id, code, message, Severity.INFO, joint, True)
        )

    def alive(self) -> None:
        """Heartbeat: the peer is still there."""
        self._port.alive(self.slave_id)

    async def connection_lost(self, reason: str) -> None:
        """The hardware behind this slave is gone, but the driver stays and keeps trying.

        The loss policy applies as for a lost slave; the slave stays attached and shows as
        disconnected until `connection_restored`.
        """
        await self._port.post(LinkMsg(self.slave_id, False, reason))

    async def connection_restored(self, reason: str = "reconnected") -> None:
        """The hardware answers again (nothing moves until a new target arrives)."""
        await self._port.post(LinkMsg(self.slave_id, True, reason))

    async def rejoin(self, reason: str, joints: Mapping[str, float] | None = None) -> None:
        """The arm behind this slave may be somewhere else than the robot's targets say (it
        was calibrated anew, or moved by hand with torque off): it joins again, from `joints`
        (degrees, read just now) or else from its next report (specs/robot-model.md, "Slaves
        that join")."""
        await self._port.post(
            RejoinMsg(self.slave_id, reason, None if joints is None else dict(joints))
        )

    async def detach(self, reason: str = "slave left") -> None:
        """Leave the robot."""
        await self._port.leave("slave", self.slave_id, lost=False, reason=reason)

    async def lost(self, reason: str = "connection lost") -> None:
        """Report that this slave is gone (the loss policy applies)."""
        await self._port.leave("slave", self.slave_id, lost=True, reason=reason)
