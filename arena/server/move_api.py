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

import functools
import threading
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from typing import Any

import msgspec
import trio
from quart import Blueprint, current_app, g

from arena.drivers.planned_move import PlannedMove
from arena.extras import require
from arena.protocol.errors import ArenaError, ErrorCode
from arena.protocol.rest import MoveBody
from arena.robot import collision, planning
from arena.robot.events import StateChanged
from arena.robot.handle import Robot
from arena.robot.motion import Command, CommandResult, resolve_command
from arena.robot.safety_types import Mode
from arena.server import convert
from arena.server.base import ArenaApp, error_response, read_body
from arena.server.hand_api import HandMove, answer, command_pose, plan_pose
from arena.server.interventions_api import operator_of

blueprint = Blueprint("move", __name__)

#: Plans made at once on one server (each keeps a core busy); more wait for a turn.
MAX_PLANS = 2


def _app() -> ArenaApp:
    return current_app  # type: ignore[return-value]


@dataclass
class _Planning:
    """The server's plans: a thread for each of at most MAX_PLANS, one per robot."""

    threads: trio.CapacityLimiter = field(default_factory=lambda: trio.CapacityLimiter(MAX_PLANS))
    robots: set[str] = field(default_factory=set)


def _planning(app: ArenaApp) -> _Planning:
    found: _Planning = app.extensions.setdefault("arena-planning", _Planning())
    return found


class PathNotFound(ArenaError):
    """NO_PATH, with what blocks (for the REST answer's `blocked`)."""

    def __init__(self, reason: planning.NoPath) -> None:
        super().__init__(ErrorCode.NO_PATH, f"No path to the goal: {reason.reason}.")
        self.hit = reason.hit


@blueprint.post("/api/robots/<robot_id>/move")
async def move(robot_id: str) -> dict[str, Any]:
    """Move to a joint or pose goal: straight (one command), or along a planned path."""
    robot = _app().manager.get(robot_id)
    body: MoveBody = await read_body(MoveBody)
    check_goal(body)
    if body.plan:
        return await _planned(robot, body)
    master_id = operator_of(robot, g.principal)  # an operator's intervention: as its master

    async def send(command: Command) -> CommandResult:
        return await robot.command(command, master_id)

    result, solved = await move_straight(robot, body, send, "rest")
    if not result.accepted:
        assert result.code is not None
        raise ArenaError(result.code, result.message)
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


async def plan_move(
    app: ArenaApp, robot: Robot, data: MoveBody, master_id: str | None
) -> planning.PlannedPath:
    """The path to `data`'s goal from the joints' goals, planned in a thread; `master_id`: the
    master it is planned for (None: the robot must have none). Raises what refuses it."""
    if data.duration is not None or (data.pose is not None and data.pose.duration is not None):
        raise ArenaError(
            ErrorCode.INVALID_VALUE,
            "A planned move is timed by the joints' limits: leave `duration` out (`speed` "
            "slows it).",
        )
    # (in a thread: the first import of OMPL takes most of a second, the loop must not wait)
    await trio.to_thread.run_sync(require, "plan", "A planned move")
    guard = collision.for_model(robot.model)
    if guard is None:
        raise ArenaError(
            ErrorCode.INVALID_CONFIG,
            f"Robot type {robot.model.robot_type!r} has no collision model (no meshes): "
            "there is nothing to plan around.",
        )
    _free_to_move(robot, master_id)
    start = {joint.name: joint.goal for joint in robot.snapshot().joints}
    goal = dict(start)
    if data.pose is not None:
        solved = await plan_pose(robot, data.pose, "move")
        goal.update((joint.name, joint.value) for joint in solved.command.joints)
    else:
        assert data.joints is not None
        goals, _ = resolve_command(robot.model, Command.of(data.joints))  # named, finite
        goal.update((resolved.name, resolved.value) for resolved in goals)
    budget = planning.DEFAULT_BUDGET if data.budget is None else data.budget / 1000.0
    speed = 1.0 if data.speed is None else data.speed
    workspace = robot.workspace
    plan = functools.partial(
        planning.plan, robot.model, guard, workspace, start, goal, budget=budget, speed=speed
    )
    path = await _plan_off_the_loop(_planning(app), robot, plan)
    _free_to_move(robot, master_id)
    now = {joint.name: joint.goal for joint in robot.snapshot().joints}
    if now != start or robot.workspace is not workspace:
        raise ArenaError(
            ErrorCode.NO_PATH,
            "The arm was moved, or its workspace changed, while the path was planned: ask again.",
        )
    return path


def _free_to_move(robot: Robot, master_id: str | None) -> None:
    """Refuse at once what playing the plan would be refused: an e-stopped robot, or one
    another master holds (`master_id`: the master the plan is for, None for none)."""
    snapshot = robot.snapshot()
    if snapshot.mode is Mode.ESTOPPED:
        raise ArenaError(ErrorCode.ESTOPPED, "The robot is e-stopped: reset it first.")
    if snapshot.master is not None and snapshot.master.peer_id != master_id:
        raise ArenaError(
            ErrorCode.MASTER_ACTIVE,
            f"Robot is controlled by master {snapshot.master.peer_id!r}: a planned move takes "
            "no robot a master holds.",
        )


async def _plan_off_the_loop(plans: _Planning, robot: Robot, plan: Any) -> planning.PlannedPath:
    """`plan(cancel=...)` in a thread (one per robot at a time), ended early by an e-stop of
    the robot or by the request going away."""
    if robot.robot_id in plans.robots:
        raise ArenaError(
            ErrorCode.LIMIT_REACHED,
            "A path is being planned for this robot already: one at a time.",
        )
    plans.robots.add(robot.robot_id)
    cancel = threading.Event()
    refusal: planning.NoPath | None = None

    async def watch() -> None:
        with robot.subscribe(maxlen=16, kinds=[StateChanged]) as events:
            while robot.snapshot().mode is not Mode.ESTOPPED:
                await events.get()
            cancel.set()

    try:
        async with trio.open_nursery() as nursery:
            nursery.start_soon(watch)
            try:
                path: planning.PlannedPath = await trio.to_thread.run_sync(
                    functools.partial(plan, cancel=cancel),
                    abandon_on_cancel=True,
                    limiter=plans.threads,
                )
            except planning.NoPath as reason:
                refusal = reason  # raised outside the nursery: not in an exception group
            nursery.cancel_scope.cancel()
    finally:
        cancel.set()  # (a request gone: the abandoned thread stops at its next check)
        plans.robots.discard(robot.robot_id)
    if refusal is not None and refusal.cancelled:
        raise ArenaError(ErrorCode.ESTOPPED, "The robot was e-stopped while its path was planned.")
    if refusal is not None:
        raise PathNotFound(refusal)
    return path


@blueprint.errorhandler(PathNotFound)
async def no_path(error: PathNotFound) -> tuple[dict[str, Any], int]:
    """NO_PATH with what blocks: two links, or a link and `floor` or a keep-out box's name."""
    _app().metrics.message_errors[str(error.code)] += 1
    body, status = error_response(error.code, error.message)
    body["error"]["blocked"] = None if error.hit is None else [error.hit.first, error.hit.second]
    return body, status
