"""`arena script FILE --url ... --robot ID`: a script on this machine as the master of a robot on
an Arena server, over the public API only (the master's WebSocket). The same worker and the same
`ScriptMaster` run as on the server, with the same API; the server applies every rule to the
commands (specs/scripts.md).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import trio

from arena.client import MasterSession
from arena.client.errors import ArenaClientError
from arena.protocol import messages as wire
from arena.protocol.errors import ErrorCode, Severity
from arena.robot.model import load_robot_model
from arena.robot.motion import Command, CommandResult
from arena.script.master import NO_PLANNER, ScriptMaster, ScriptSettings
from arena.script.wire import MoveToPose, PlannedJoints

log = logging.getLogger(__name__)

#: The server's answers to a message it does not know (a server without planned moves).
UNKNOWN = frozenset({"UNKNOWN_MESSAGE_TYPE", "INVALID_MESSAGE"})


def _refused(error: ArenaClientError) -> CommandResult:
    try:
        code = ErrorCode(error.code)
    except ValueError:  # DISCONNECTED, TIMEOUT: this link no longer drives the robot
        code = ErrorCode.NOT_OWNER
    return CommandResult.refused(code, error.message)


@dataclass
class SessionArm:
    """`ScriptArm` over a master's session: the joints as the server last reported them,
    commands answered by their acknowledgments, faults to the log."""

    session: MasterSession
    faults: list[tuple[str, str]] = field(default_factory=list)

    def joint_values(self) -> tuple[dict[str, float], dict[str, float]]:
        """See `ScriptArm.joint_values`."""
        commanded: dict[str, float] = {}
        measured: dict[str, float] = {}
        for name, entry in self.session.joints.items():
            value = entry.get("virtual_value", entry.get("value"))
            if value is not None:
                commanded[name] = float(value)
            if entry.get("real_value") is not None:
                measured[name] = float(entry["real_value"])
        return commanded, measured

    async def command(self, command: Command) -> CommandResult:
        """See `ScriptArm.command`."""
        joints = {goal.name: goal.value for goal in command.joints}
        extra = {} if command.duration is None else {"duration": command.duration * 1000.0}
        metadata = {"source": command.source} if command.source else {}
        try:
            await self.session.command(joints, metadata=metadata, **extra)
        except ArenaClientError as error:
            return _refused(error)
        return CommandResult(True)

    async def pose(
        self, data: wire.PoseData, source: str
    ) -> tuple[CommandResult, dict[str, float]]:
        """The `pose` message: the server solves the joints (their targets are not told)."""
        try:
            await self.session.pose(
                data.position, data.orientation, gripper=data.gripper, duration=data.duration
            )
        except ArenaClientError as error:
            return _refused(error), {}
        return CommandResult(True), {}

    async def planned(
        self, request: MoveToPose | PlannedJoints, source: str
    ) -> tuple[CommandResult, dict[str, float]]:
        """The `move` message with `plan`, where the server plans moves."""
        if isinstance(request, PlannedJoints):
            goal: dict[str, object] = {"joints": dict(request.joints)}
        else:
            pose: dict[str, object] = {"position": list(request.position)}
            if request.orientation is not None:
                pose["orientation"] = list(request.orientation)
            goal = {"pose": pose}
        try:
            await self.session.move(goal, plan=True)
        except ArenaClientError as error:
            if error.code in UNKNOWN:
                return CommandResult.refused(ErrorCode.NOT_INSTALLED, NO_PLANNER), {}
            return _refused(error), {}
        return CommandResult(True), {}

    @property
    def paused(self) -> bool:
        """The server paused this master (its `pause` message, until `resume`)."""
        return self.session.paused

    @property
    def pauses(self) -> int:
        """The server's `pause` messages so far."""
        return self.session.pauses

    @property
    def stops(self) -> int:
        """The server's `stopped` messages so far."""
        return self.session.stop_count

    @property
    def last_stop(self) -> str:
        """The newest `stopped` message's sentence."""
        return str(self.session.stops[-1].get("message", "")) if self.session.stops else ""

    async def wait_resumed(self) -> None:
        """See `paused`."""
        await self.session.wait_resumed()

    def fault(self, source: str, code: ErrorCode, message: str, severity: Severity) -> None:
        """Logged here (and printed by `arena script`)."""
        self.faults.append((str(code), message))
        log.warning("%s: %s (%s): %s", source, code, severity, message)


def ended(session: MasterSession) -> bool:
    """The robot is e-stopped, or has let this master go."""
    return session.detached is not None or (session.state or {}).get("mode") == "estopped"


async def run_remote(
    settings: ScriptSettings,
    url: str,
    robot_id: str,
    api_key: str | None = None,
    takeover: bool = False,
) -> tuple[ScriptMaster, SessionArm]:
    """Run the script here as the master of `robot_id` there until it ends or the robot ends
    it (an e-stop, a takeover); the master (its outcome, lines, counters) and the arm."""
    from arena.client import AsyncArena

    async with AsyncArena(url, api_key) as arena:
        robot = await arena.robot(robot_id)
    master = ScriptMaster(settings, load_robot_model(robot["robot_type"]))
    async with MasterSession.open(
        url, robot_id, takeover=takeover, master_id=master.identity, api_key=api_key
    ) as session:
        await session.wait_for(lambda s: bool(s.joints), timeout=10)
        if ended(session):
            raise ArenaClientError("ESTOPPED", f"Robot {robot_id!r} is e-stopped: reset it first.")
        arm = SessionArm(session)
        async with trio.open_nursery() as nursery:

            async def let_go() -> None:
                # An e-stop (or the robot letting this master go: a takeover) ends the script
                # at once, its worker killed, as on the server.
                await session.wait_for(ended, timeout=math.inf)
                nursery.cancel_scope.cancel()

            nursery.start_soon(let_go)
            await master.drive(arm)
            nursery.cancel_scope.cancel()
        if ended(session):  # (whether its worker saw a refusal first or not)
            state = session.state or {}
            master.outcome = (
                f"the robot was e-stopped ({state.get('estop_reason')}): the script ended"
                if state.get("mode") == "estopped"
                else f"the robot let it go: {session.detached}"
            )
    return master, arm
