"""Manual control over REST (`PUT .../joints`, `PUT .../pose`, `POST .../move`): whom a
caller commands as, and the refusal a caller meets while a master drives the robot.

An operator who intervenes with `POST .../intervention {}` is the robot's master
`operator:NAME`; that caller's REST commands go as that master, anyone else's are refused.
"""

from __future__ import annotations

import trio

from arena.protocol.errors import ArenaError, ErrorCode
from arena.robot.core import MANUAL_SOURCE
from arena.robot.events import MotionStopped, StateChanged, TargetsSent
from arena.robot.handle import Robot
from arena.robot.motion import Command, CommandResult
from arena.robot.safety import Mode
from arena.server.identity import Principal

#: The kind of the master an operator intervenes as over REST (`PUT .../joints`).
OPERATOR_KIND = "operator"


def operator_id(principal: Principal) -> str:
    """The master id an operator intervening over REST holds the robot under."""
    return f"operator:{principal.audit_name()}"


def operator_of(robot: Robot, principal: Principal) -> str | None:
    """The caller's master id if the caller intervenes on `robot` over REST, else None (its
    `PUT .../joints` is then manual control)."""
    master = robot.snapshot().master
    if (
        master is not None
        and master.kind == OPERATOR_KIND
        and master.peer_id == operator_id(principal)
    ):
        return master.peer_id
    return None


def master_active(robot: Robot, lead: str) -> ArenaError | None:
    """MASTER_ACTIVE for a REST move while a master drives `robot`: `lead` (what is refused),
    then the master in words and the ways out. None when no master drives it (any more)."""
    snapshot = robot.snapshot()
    master = snapshot.master
    if master is None:
        return None
    route = f"/api/robots/{robot.robot_id}"
    who = f"master {master.peer_id!r}" + (f" ({master.description})" if master.description else "")
    if snapshot.paused_master is not None:  # someone intervenes: only the hand-back frees it
        ways = f"wait until it hands back (DELETE {route}/intervention)"
    else:
        ways = (
            f"wait for it to end, pause it and take over with POST {route}/intervention, "
            f"or detach it with DELETE {route}/master"
        )
    return ArenaError(ErrorCode.MASTER_ACTIVE, f"{lead} while {who} drives the robot: {ways}.")


def refusal(robot: Robot, result: CommandResult) -> ArenaError:
    """The error for a REST command `result` refused: its own, or, for MASTER_ACTIVE, one
    that says which master holds the robot and what to do."""
    assert result.code is not None
    if result.code == ErrorCode.MASTER_ACTIVE:
        found = master_active(robot, "Manual control is off")
        if found is not None:
            return found
    return ArenaError(result.code, result.message)


async def move(
    robot: Robot, command: Command, master_id: str | None, wait: float | None
) -> tuple[CommandResult, str | None]:
    """Command `robot` as `master_id` (None: manual control). With `wait` seconds, answer when
    the arm is on the goals the command set (its targets there, at rest), not at acceptance:
    the result and None; or why it is not there (another command moved the goals, or the time
    ran out). A move the collision guard stops on its way raises its COLLISION, and an e-stop
    ESTOPPED: the move ended short (the robot's `last_stop` says where the arm holds)."""
    if not wait:
        return await robot.command(command, master_id), None
    source = master_id or MANUAL_SOURCE
    with robot.subscribe(kinds=(TargetsSent, MotionStopped, StateChanged)) as events:
        result = await robot.command(command, master_id)
        if not result.accepted:
            return result, None
        goals = {joint.name: joint.goal for joint in robot.snapshot().joints}
        with trio.move_on_after(wait):
            while True:
                # (a trajectory's last target is its goal: there when every target is)
                joints = robot.snapshot().joints
                if any(joint.goal != goals[joint.name] for joint in joints):
                    return result, "another command changed the goals before the arm got there"
                if all(joint.virtual_value == goals[joint.name] for joint in joints):
                    return result, None
                try:
                    event = await events.get()
                except trio.EndOfChannel:
                    raise ArenaError(
                        ErrorCode.ROBOT_STOPPED, "The robot stopped before the arm got there."
                    ) from None
                if isinstance(event, MotionStopped) and event.source == source:
                    raise ArenaError(ErrorCode.COLLISION, event.message)
                if isinstance(event, StateChanged) and event.mode is Mode.ESTOPPED:
                    why = event.estop_reason or event.cause
                    raise ArenaError(ErrorCode.ESTOPPED, f"E-stopped on the way ({why}).")
        return result, f"not there after {wait:g} s"
