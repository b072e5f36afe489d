"""`POST /api/robots/{id}/move`: a joint or pose goal, reached by one command (the straight
way the collision guard checks) or, with `"plan": true`, by a path found around the table,
the keep-out boxes and the arm itself and played as a master of its own (specs/cartesian.md,
"Planned paths").

The plan is made in a thread: OMPL calls the guard's model (pure Python) for every check, so
the thread holds the GIL only while Python runs, which gives it up every switch interval (5
ms): the event loop, and with it every e-stop, keeps its turns. An e-stop of the robot ends
its plan at the planner's next check.
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable
from typing import Any

import msgspec
from quart import Blueprint, current_app, g

from arena.drivers.planned_move import PlannedMove
from arena.protocol.errors import ArenaError, ErrorCode
from arena.protocol.rest import MoveBody
from arena.robot.handle import Robot
from arena.robot.motion import Command, CommandResult
from arena.server import convert
from arena.server.base import ArenaApp, error_response, read_body
from arena.server.hand_api import HandMove, answer, command_pose
from arena.server.manual import operator_of, refusal
from arena.server.planned_moves import PathNotFound, plan_move

blueprint = Blueprint("move", __name__)

#: The refusal of `joints` given as `PUT .../joints`'s list, and what this route takes instead.
_LISTED = "Invalid `joints`: Expected `object"
_JOINTS_FORM = 'Here `joints` maps names to degrees, e.g. {"Rotation": 10}.'


def _app() -> ArenaApp:
    return current_app  # type: ignore[return-value]


@blueprint.post("/api/robots/<robot_id>/move")
async def move(robot_id: str) -> dict[str, Any]:
    """Move to a joint or pose goal: straight (one command), or along a planned path."""
    robot = _app().manager.get(robot_id)
    try:
        body: MoveBody = await read_body(MoveBody)
    except ArenaError as error:
        if error.code is ErrorCode.INVALID_BODY and error.message.startswith(_LISTED):
            raise ArenaError(error.code, f"{error.message} {_JOINTS_FORM}") from None
        raise
    check_goal(body)
    if body.plan:
        return await _planned(robot, body)
    master_id = operator_of(robot, g.principal)  # an operator's intervention: as its master

    async def send(command: Command) -> CommandResult:
        return await robot.command(command, master_id)

    result, solved = await move_straight(robot, body, send, "rest")
    if not result.accepted:
        raise refusal(robot, result)
    if solved is not None:
        return {**answer(result, solved), "plan": False}
    ack: dict[str, Any] = msgspec.to_builtins(convert.ack(result).data)
    return {**ack, "plan": False}


def check_goal(data: MoveBody) -> None:
    """One goal, and `budget` and `speed` only with `plan` (INVALID_VALUE)."""
    if (data.joints is None) == (data.pose is None):
        raise ArenaError(ErrorCode.INVALID_VALUE, "Give one goal: `joints` or `pose`.")
    if not data.plan and (data.budget is not None or data.speed is not None):
        raise ArenaError(
            ErrorCode.INVALID_VALUE, "`budget` and `speed` are for a planned move (`plan`)."
        )


async def move_straight(
    robot: Robot,
    data: MoveBody,
    send: Callable[[Command], Awaitable[CommandResult]],
    source: str,
) -> tuple[CommandResult, HandMove | None]:
    """A move without a plan: one command through `send` (and the pose it was solved from)."""
    if data.pose is not None:
        if data.duration is not None:
            raise ArenaError(ErrorCode.INVALID_VALUE, "A pose's `duration` goes in `pose`.")
        return await command_pose(robot, data.pose, send, source)
    assert data.joints is not None
    duration = None if data.duration is None else data.duration / 1000.0
    command = Command.of(data.joints, duration)
    return await send(Command(command.joints, duration, source)), None


async def _planned(robot: Robot, body: MoveBody) -> dict[str, Any]:
    """Plan (in a thread), then play the path as a master of its own."""
    path = await plan_move(_app(), robot, body, None)
    master_id = await robot.attach_master(PlannedMove(path))
    return {
        "robot": robot.robot_id,
        "plan": True,
        "master": master_id,
        "straight": path.straight,
        "duration": round(path.duration * 1000.0, 1),
        "planning": round(path.planning * 1000.0, 1),
        "waypoints": [{n: round(v, 4) for n, v in corner.items()} for corner in path.waypoints],
    }


@blueprint.errorhandler(PathNotFound)
async def no_path(error: PathNotFound) -> tuple[dict[str, Any], int]:
    """NO_PATH with what blocks: two links, or a link and `floor` or a keep-out box's name."""
    _app().metrics.message_errors[str(error.code)] += 1
    body, status = error_response(error.code, error.message)
    body["error"]["blocked"] = None if error.hit is None else [error.hit.first, error.hit.second]
    return body, status
