"""Where the hand is and where it should go, over REST and from masters (specs/cartesian.md).

`GET /api/robots/{id}/pose` gives the hand's pose from the measured joints and the commanded
one; `PUT /api/robots/{id}/pose` (and the master message `pose`) solves the inverse kinematics
from where the joints are commanded to be and sends the joint command through every rule, as
`PUT .../joints` does.
"""

from __future__ import annotations

import math
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from typing import Any

import msgspec
import trio
from quart import Blueprint, current_app, g

from arena.protocol import messages as wire
from arena.protocol.errors import ArenaError, ErrorCode
from arena.protocol.rest import TeleopBody
from arena.robot.cartesian import Hand, HandPose, Solution, hand_for, normalized
from arena.robot.collision import Hit
from arena.robot.handle import Robot
from arena.robot.links import RobotView
from arena.robot.motion import Command, CommandResult
from arena.robot.teleop import TeleopSettings, settings_of
from arena.robot.workspace import point_inside
from arena.server import convert
from arena.server.base import ArenaApp, error_response, read_body
from arena.server.manual import operator_of, refusal

blueprint = Blueprint("hand", __name__)


def _app() -> ArenaApp:
    return current_app  # type: ignore[return-value]


def hand_of(robot: Robot) -> Hand:
    """The robot's hand, or INVALID_CONFIG when its robot type names none."""
    hand = hand_for(robot.model)
    if hand is None:
        raise ArenaError(
            ErrorCode.INVALID_CONFIG,
            f"Robot type {robot.model.robot_type!r} names no [end_effector] in its robot.toml: "
            "poses need the link of its hand.",
        )
    return hand


def pose_json(pose: HandPose | None) -> dict[str, Any] | None:
    """A pose as the API shows it."""
    if pose is None:
        return None
    return {
        "position": [round(v, 6) for v in pose.position],
        "orientation": [round(v, 6) for v in pose.orientation],
        "gripper": pose.gripper,
    }


def pose_view(robot: Robot) -> dict[str, Any]:
    """`GET .../pose`: the measured pose (None until an arm reports every joint of the chain),
    the commanded one (the joints' goals: where the hand is told to go), and the frames."""
    hand = hand_of(robot)
    _, real = robot.joint_values()
    goals = {joint.name: joint.goal for joint in robot.snapshot().joints}
    return {
        "link": hand.link,
        "frame": hand.root,
        "measured": pose_json(hand.pose(dict(real))),
        "commanded": pose_json(hand.pose(goals)),
    }


@dataclass(frozen=True, slots=True)
class HandMove:
    """A pose turned into a joint command, with the solution it came from."""

    command: Command
    solution: Solution


class Unreachable(ArenaError):
    """UNREACHABLE, with the nearest pose found (for the REST answer's `nearest`)."""

    def __init__(self, solution: Solution, with_orientation: bool) -> None:
        degrees = math.degrees(solution.angle)
        turned = f" and turned {degrees:.1f} degrees" if with_orientation else ""
        super().__init__(
            ErrorCode.UNREACHABLE,
            f"No pose of the arm puts its hand there: the nearest found is "
            f"{solution.distance * 1000:.1f} mm away{turned}.",
        )
        self.solution = solution


class GoalInside(ArenaError):
    """COLLISION: the pose's point itself lies in the table or a keep-out box (`hit`: the hand
    and what it is in; `where`: the words). Said instead of UNREACHABLE when the solver fell
    short of such a point: no pose could take the hand there, in reach or not."""

    def __init__(self, link: str, what: str, where: str) -> None:
        super().__init__(
            ErrorCode.COLLISION,
            f"The goal is {where}: the {link} cannot go there; command refused.",
        )
        self.hit = Hit(link, what)
        self.where = where


async def plan_pose(robot: Robot, data: wire.PoseData, source: str) -> HandMove:
    """Solve `data` from the joints' commanded goals; raises INVALID_VALUE for a zero
    orientation, `GoalInside` when the solver fell short of a point in the table or a
    keep-out box, and `Unreachable` when no pose gets within the solver's tolerances. (A
    point in the table the solver does reach is the collision guard's to refuse, or to stop
    short of under its `stop-short` policy.)"""
    hand = hand_of(robot)
    orientation = None
    if data.orientation is not None:
        try:
            q = data.orientation
            orientation = normalized((q[0], q[1], q[2], q[3]))
        except ValueError as exc:
            raise ArenaError(ErrorCode.INVALID_VALUE, f"`orientation`: {exc}.") from None
    if data.gripper is not None and hand.gripper is None:
        raise ArenaError(
            ErrorCode.INVALID_VALUE,
            f"Robot type {robot.model.robot_type!r} names no gripper joint: leave `gripper` out.",
        )
    if data.gripper is not None and not math.isfinite(data.gripper):
        raise ArenaError(ErrorCode.INVALID_VALUE, "`gripper` must be a finite number.")
    start = {j.name: j.goal for j in robot.snapshot().joints}
    position = (data.position[0], data.position[1], data.position[2])
    solution = await solve_off_the_loop(hand, position, orientation, start)
    if not solution.reached:
        inside = point_inside(robot.workspace, position)
        if inside is not None:
            raise GoalInside(hand.link, *inside)
        raise Unreachable(solution, orientation is not None)
    goals = [wire.JointValue(name, value) for name, value in solution.joints.items()]
    if data.gripper is not None and hand.gripper is not None:
        goals.append(wire.JointValue(hand.gripper.name, data.gripper))
    duration = None if data.duration is None else data.duration / 1000.0
    return HandMove(Command(tuple(goals), duration, source), solution)


async def hand_command(view: RobotView, data: wire.PoseData, source: str) -> Command:
    """A pose as the joint command that gets the hand there, for a script master (its
    `hand_mover`): solved as `PUT .../pose` and the `pose` message solve it."""
    if not isinstance(view, Robot):
        raise TypeError("a script master drives a robot of this server")
    return (await plan_pose(view, data, source)).command


async def solve_off_the_loop(
    hand: Hand, position: tuple[float, float, float], orientation: Any, start: dict[str, float]
) -> Solution:
    """The solve, in a thread: most take a few milliseconds, but a far or awkward target takes
    every start's iterations, and the robots' control ticks must not wait for them (pure
    Python holds the GIL, but gives it up every switch interval, 5 ms)."""
    return await trio.to_thread.run_sync(hand.solve, position, orientation, start)


async def command_pose(
    robot: Robot,
    data: wire.PoseData,
    send: Callable[[Command], Awaitable[CommandResult]],
    source: str,
) -> tuple[CommandResult, HandMove]:
    """Solve and send a pose through `send` (manual control, or a master's link)."""
    move = await plan_pose(robot, data, source)
    return await send(move.command), move


def answer(result: CommandResult, move: HandMove) -> dict[str, Any]:
    """The REST answer to an accepted pose: the command's acknowledgment and the joints."""
    ack: dict[str, Any] = msgspec.to_builtins(convert.ack(result).data)
    ack["joints"] = {name: round(value, 4) for name, value in move.solution.joints.items()}
    ack["distance"] = move.solution.distance
    return ack


@blueprint.get("/api/robots/<robot_id>/pose")
async def get_pose(robot_id: str) -> dict[str, Any]:
    """The hand's pose, measured and commanded."""
    return pose_view(_app().manager.get(robot_id))


@blueprint.put("/api/robots/<robot_id>/pose")
async def put_pose(robot_id: str) -> dict[str, Any]:
    """Move the hand to a pose (manual control, refused while a master drives the robot)."""
    robot = _app().manager.get(robot_id)
    body: wire.PoseData = await read_body(wire.PoseData)
    master_id = operator_of(robot, g.principal)  # an operator's intervention: as its master

    async def send(command: Command) -> CommandResult:
        return await robot.command(command, master_id)

    result, move = await command_pose(robot, body, send, "rest")
    if not result.accepted:
        raise refusal(robot, result)
    return answer(result, move)


@blueprint.errorhandler(Unreachable)
async def unreachable(error: Unreachable) -> tuple[dict[str, Any], int]:
    """UNREACHABLE with the nearest pose found: how far, how turned, and its joints."""
    _app().metrics.message_errors[str(error.code)] += 1
    body, status = error_response(error.code, error.message)
    nearest = error.solution
    body["error"]["nearest"] = {
        "distance": nearest.distance,
        "angle": math.degrees(nearest.angle),
        "joints": nearest.joints,
    }
    return body, status


def teleop_json(settings: TeleopSettings) -> dict[str, Any]:
    """Teleoperation settings as the API shows them (the dead-man time in milliseconds)."""
    return {
        "box": {"min": list(settings.low), "max": list(settings.high)},
        "deadman": round(settings.deadman * 1000.0, 3),
    }


@blueprint.get("/api/robots/<robot_id>/teleop")
async def get_teleop(robot_id: str) -> dict[str, Any]:
    """Where `ee_velocity` may take the hand, and its dead-man time."""
    robot = _app().manager.get(robot_id)
    return teleop_json(settings_of(robot, hand_of(robot), robot.workspace))


@blueprint.put("/api/robots/<robot_id>/teleop")
async def put_teleop(robot_id: str) -> dict[str, Any]:
    """Change the box and the dead-man time (what is left out is kept)."""
    robot = _app().manager.get(robot_id)
    body: TeleopBody = await read_body(TeleopBody)
    settings = settings_of(robot, hand_of(robot), robot.workspace)
    low, high, deadman = settings.low, settings.high, settings.deadman
    if body.box is not None:
        low = (body.box.min[0], body.box.min[1], body.box.min[2])
        high = (body.box.max[0], body.box.max[1], body.box.max[2])
        if not all(a < b for a, b in zip(low, high, strict=True)):
            raise ArenaError(
                ErrorCode.INVALID_VALUE, "`box`: each of `min` must be below its `max`."
            )
    if body.deadman is not None:
        deadman = body.deadman / 1000.0
    chosen = TeleopSettings(low, high, deadman)
    robot.teleop = chosen  # from the next tick on
    return teleop_json(chosen)
