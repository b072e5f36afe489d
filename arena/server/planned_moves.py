"""Planned moves for every caller: a path planned off the event loop, one plan per robot and
at most `MAX_PLANS` a server (specs/cartesian.md, "Planned paths"). The REST route
(`arena.server.move_api`), the `move` master message and a script master's `plan=True` all
plan here."""

from __future__ import annotations

import functools
import threading
from dataclasses import dataclass, field
from typing import Any

import trio

from arena.drivers.planned_move import PlannedMove
from arena.extras import require
from arena.protocol import messages as wire
from arena.protocol.errors import ArenaError, ErrorCode
from arena.protocol.rest import MoveBody
from arena.robot import collision, planning
from arena.robot.events import StateChanged
from arena.robot.handle import Robot
from arena.robot.links import MasterLink
from arena.robot.motion import Command, CommandResult, resolve_command
from arena.robot.safety_types import Mode
from arena.script.master import ScriptMaster
from arena.script.wire import MoveToPose, PlannedJoints
from arena.server.base import ArenaApp
from arena.server.hand_api import GoalInside, hand_command, plan_pose
from arena.server.manual import master_active

#: Plans made at once on one server (each keeps a core busy); more wait for a turn.
MAX_PLANS = 2


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
        try:
            solved = await plan_pose(robot, data.pose, "move")
        except GoalInside as inside:  # as the planner says a goal pose that collides
            raise PathNotFound(
                planning.NoPath(f"the goal itself is {inside.where}", inside.hit)
            ) from None
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
        refused = master_active(robot, "A planned move takes no robot a master holds")
        if refused is not None:
            raise refused


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


def equip_script(app: ArenaApp, driver: object) -> None:
    """Give a script master the server's inverse kinematics and planner (other drivers: as
    they are)."""
    if isinstance(driver, ScriptMaster):
        driver.hand_mover = hand_command
        driver.planner = functools.partial(script_plan, app)


async def script_plan(
    app: ArenaApp, link: MasterLink, request: MoveToPose | PlannedJoints, source: str
) -> tuple[CommandResult, dict[str, float]]:
    """A script's planned move: planned for its master, then played on its link as its own
    commands (paused with it); the answer is the last pose's, with the goal's joints."""
    if isinstance(request, PlannedJoints):
        data = MoveBody(joints=dict(request.joints), plan=True)
    else:
        orientation = None if request.orientation is None else list(request.orientation)
        pose = wire.PoseData(list(request.position), orientation, request.gripper)
        data = MoveBody(pose=pose, plan=True)
    robot = app.manager.get(link.robot.robot_id)  # (the link's view: no planning there)
    path = await plan_move(app, robot, data, link.master_id)
    player = PlannedMove(path, source=source)
    await player.run(link)
    goal = dict(path.samples[-1][1]) if path.samples else {}
    if player.refusals and player.refusals[-1][0] is not ErrorCode.RATE_LIMITED:
        code, message = player.refusals[-1]  # the pose it ended on
        return CommandResult.refused(code or ErrorCode.INVALID_VALUE, message), goal
    return CommandResult(True), goal
