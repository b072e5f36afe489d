"""A Python script as a robot's master: the script runs in a worker process of its own
(`arena.script.worker`), and its requests (move the joints, move to a pose, the gripper, wait,
read) come over the worker's pipe to this master, which carries them out as the robot's master
through every rule a master's command meets (specs/scripts.md).

The master is autonomous: an e-stop (or a takeover, a detach) cancels it and the worker is
killed at once. A paused robot holds every request until it resumes. The worker's requests and
output lines are paced, so a script in a tight loop cannot flood the robot or the log.
"""

from __future__ import annotations

import logging
import math
import sys
from collections import deque
from collections.abc import Awaitable, Callable, Mapping
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, ClassVar, Protocol

import msgspec
import trio

from arena.child import Child
from arena.protocol import messages as wire
from arena.protocol.errors import ArenaError, ErrorCode, Severity
from arena.robot.cartesian import hand_for
from arena.robot.links import MasterLink, RobotView
from arena.robot.model import RobotModel
from arena.robot.motion import Command, CommandResult
from arena.script.wire import (
    MAX_FRAME,
    Answer,
    Failed,
    Finished,
    FrameError,
    Gripper,
    Line,
    MoveJoints,
    MoveToPose,
    PlannedJoints,
    Read,
    Request,
    Wait,
    decode_from_worker,
    encode,
)

log = logging.getLogger(__name__)

#: How a worker is started: this interpreter, the worker module (the script's path follows).
WORKER = (sys.executable, "-m", "arena.script.worker")
#: Scripts one process runs at once at most (each a Python process of its own).
MAX_WORKERS = 8
#: Seconds between looks at the joints while a move runs (the end of a move is seen this late).
POLL = 0.02
#: A move is over when every joint it moves is this close to its target (degrees)...
TOLERANCE = 0.05
#: ...or when none of them has moved for this long once they moved (`MoveEnd`).
STILL = 0.25

#: A command's result and the joints' targets it set (empty: not known on this side).
Sent = tuple[CommandResult, dict[str, float]]
#: Turns a pose into the joint command that gets the hand there (the server's inverse
#: kinematics, `arena.server.hand_api`); raises `ArenaError` (UNREACHABLE, ...) if none does.
HandMover = Callable[[RobotView, wire.PoseData, str], Awaitable[Command]]
#: A planned move (the `move` message with `plan`), played on the master's link: the result
#: and the goal's joints.
Planner = Callable[[MasterLink, Request, str], Awaitable[tuple[CommandResult, dict[str, float]]]]


class MoveEnd:
    """When a move is over, from the joints' commanded values as they come: every joint it
    moves within `TOLERANCE` of its target (clamped to its limits), or, where the targets are
    not known here (a pose over the API) or not reached (held short), the joints having moved
    and then stood still for `STILL`. A move that has not started after `STILL` plus a quarter
    of its duration (and half a second: a slow start's first steps may not be reported) was
    already there."""

    def __init__(
        self,
        targets: Mapping[str, float],
        duration: float | None,
        started: float,
        clamp: Callable[[str, float], float],
    ) -> None:
        self.targets = {name: clamp(name, value) for name, value in targets.items()}
        self.grace = STILL + 0.5 + 0.25 * (duration or 0.0)
        self.started = started
        self.last: tuple[float, ...] | None = None
        self.moved = False
        self.still_since = started

    def over(self, commanded: Mapping[str, float], now: float) -> bool:
        """Whether the move is over, given the joints' commanded values `now`."""
        names = list(self.targets) or list(commanded)
        values = tuple(commanded.get(name, math.nan) for name in names)
        if self.targets and all(
            abs(value - self.targets[name]) <= TOLERANCE
            for name, value in zip(names, values, strict=True)
        ):
            return True
        if self.last is not None and values != self.last:
            self.moved, self.still_since = True, now
        self.last = values
        if self.moved:
            return now - self.still_since >= STILL
        return now - self.started >= self.grace


class ScriptArm(Protocol):
    """The robot as a running script sees it: a master's link on this server (`LinkArm`), a
    master's session over the API on another machine (`arena.script.remote`)."""

    def joint_values(self) -> tuple[dict[str, float], dict[str, float]]:
        """The joints' commanded values now (the trajectory's), and the measured ones (those
        an arm reports)."""

    async def command(self, command: Command) -> CommandResult:
        """Send one command as the master."""

    async def pose(
        self, data: wire.PoseData, source: str
    ) -> tuple[CommandResult, dict[str, float]]:
        """Solve and send a pose; the result and the joints' targets (empty: not known here)."""

    async def planned(
        self, request: MoveToPose | PlannedJoints, source: str
    ) -> tuple[CommandResult, dict[str, float]]:
        """A planned move; `ArenaError(NOT_INSTALLED)` where the server plans none."""

    @property
    def paused(self) -> bool:
        """The robot has the script paused."""

    @property
    def pauses(self) -> int:
        """Pauses so far (a pause and resume between two looks still counts)."""

    @property
    def stops(self) -> int:
        """This master's motions the collision guard stopped on their way, so far."""

    @property
    def last_stop(self) -> str:
        """The newest such stop in a sentence (where the arm holds, what would have met)."""

    async def wait_resumed(self) -> None:
        """Return once the script is not paused."""

    def fault(self, source: str, code: ErrorCode, message: str, severity: Severity) -> None:
        """Report a fault of the script."""


class LinkArm:
    """`ScriptArm` over a master's link to a robot of this server."""

    def __init__(
        self, link: MasterLink, hand_mover: HandMover | None, planner: Planner | None
    ) -> None:
        self.link = link
        self.hand_mover = hand_mover
        self.planner = planner

    def joint_values(self) -> tuple[dict[str, float], dict[str, float]]:
        """See `ScriptArm.joint_values`."""
        joints = self.link.robot.snapshot().joints
        commanded = {j.name: j.virtual_value for j in joints}
        measured = {j.name: j.real_value for j in joints if j.real_value is not None}
        return commanded, measured

    async def command(self, command: Command) -> CommandResult:
        """See `ScriptArm.command`."""
        return await self.link.command(command)

    async def pose(
        self, data: wire.PoseData, source: str
    ) -> tuple[CommandResult, dict[str, float]]:
        """See `ScriptArm.pose`."""
        if self.hand_mover is None:
            raise ArenaError(ErrorCode.INVALID_CONFIG, "This master cannot solve poses.")
        command = await self.hand_mover(self.link.robot, data, source)
        result = await self.link.command(command)
        return result, {goal.name: goal.value for goal in command.joints}

    async def planned(
        self, request: MoveToPose | PlannedJoints, source: str
    ) -> tuple[CommandResult, dict[str, float]]:
        """See `ScriptArm.planned`."""
        if self.planner is None:
            raise ArenaError(ErrorCode.NOT_INSTALLED, NO_PLANNER)
        return await self.planner(self.link, request, source)

    @property
    def paused(self) -> bool:
        """See `ScriptArm.paused`."""
        return self.link.paused

    @property
    def pauses(self) -> int:
        """See `ScriptArm.pauses`."""
        return self.link.pauses

    @property
    def stops(self) -> int:
        """See `ScriptArm.stops`."""
        return self.link.stops

    @property
    def last_stop(self) -> str:
        """See `ScriptArm.last_stop`."""
        return self.link.last_stop

    async def wait_resumed(self) -> None:
        """See `ScriptArm.wait_resumed`."""
        await self.link.wait_resumed()

    def fault(self, source: str, code: ErrorCode, message: str, severity: Severity) -> None:
        """Recorded and shown as a policy's faults are; never an e-stop by itself."""
        self.link.robot.report_sensor_fault(source, code, message, severity)


NO_PLANNER = (
    "This server plans no moves (planned paths, POST .../move with plan, are not part of it): "
    "move with plan=False, along the straight line the collision guard checks."
)


@dataclass(frozen=True, slots=True)
class ScriptSettings:
    """How a script runs: its file, the requests a second it may make (`rate`: reads, moves
    and waits alike; beyond it the script is slowed, never refused), the output lines a second
    it may write (`lines_rate`, after a burst of `lines_burst`; beyond, it is slowed)."""

    path: Path
    rate: float = 50.0
    lines_rate: float = 20.0
    lines_burst: int = 50


@dataclass(slots=True)
class ScriptCounters:
    """What a running script has done, shown with the robot's master."""

    requests: int = 0
    commands: int = 0  # commands the robot accepted
    refused: int = 0  # requests the robot refused (the script saw a ScriptError)
    lines: int = 0  # output lines
    pauses: int = 0  # moves the robot paused, sent again on the resume


class ScriptMaster:
    """Runs the script `settings.path` on a robot of `model`: `prepare` starts its worker,
    `run` carries out its requests until it ends (or the robot ends it), `close` kills it."""

    kind = "script"
    autonomous = True  # an e-stop ends it for good
    takes_over = False
    #: The workers started and not yet closed, all of this process's (at most MAX_WORKERS).
    live: ClassVar[set[ScriptMaster]] = set()

    def __init__(
        self,
        settings: ScriptSettings,
        model: RobotModel,
        hand_mover: HandMover | None = None,
        planner: Planner | None = None,
        command: tuple[str, ...] = WORKER,
    ) -> None:
        self.settings = settings
        self.model = model
        self.hand_mover = hand_mover
        self.planner = planner
        self.command_line = (*command, str(settings.path))
        self.child: Child | None = None
        self.counters = ScriptCounters()
        #: The script's newest output lines (its whole output is in the log).
        self.lines: deque[str] = deque(maxlen=100)
        #: How it ended: None while it runs, "" when it finished, else the fault's sentence.
        self.outcome: str | None = None
        self._next_request = 0.0
        self._line_tokens = float(settings.lines_burst)
        self._line_time = 0.0

    @property
    def identity(self) -> str:
        """`script:<file name>`, the source of its commands."""
        return f"script:{self.settings.path.name}"

    @property
    def master_id(self) -> str:
        """The id it holds the robot under: its identity."""
        return self.identity

    @property
    def description(self) -> str:
        """What it is, in words."""
        return f"script {self.settings.path}"

    def figures(self) -> dict[str, float]:
        """Its counters, shown with the robot's master."""
        return {name: float(value) for name, value in asdict(self.counters).items()}

    async def prepare(self) -> None:
        """Start the worker (the script starts; its first request waits for `run`);
        OVERLOADED when `MAX_WORKERS` run already."""
        if len(ScriptMaster.live) >= MAX_WORKERS:
            raise ArenaError(
                ErrorCode.OVERLOADED,
                f"{len(ScriptMaster.live)} scripts run already (at most {MAX_WORKERS}): "
                "detach one first.",
            )
        self.child = await Child.start(self.command_line, "the script's worker")
        ScriptMaster.live.add(self)

    async def close(self) -> None:
        """Kill the worker (nothing to do if it never started)."""
        ScriptMaster.live.discard(self)
        if self.child is not None:
            await self.child.close()

    async def run(self, link: MasterLink) -> None:
        """Carry out the script's requests until it ends or the robot ends it."""
        await self.drive(LinkArm(link, self.hand_mover, self.planner))

    async def drive(self, arm: ScriptArm) -> None:
        """Carry out the script's requests on `arm` until it ends; the worker is killed on the
        way out, whatever ends it."""
        if self.child is None:
            await self.prepare()
        assert self.child is not None
        try:
            await self._serve(arm, self.child)
        finally:
            await self.close()

    async def _serve(self, arm: ScriptArm, child: Child) -> None:
        self._next_request = self._line_time = trio.current_time()
        while True:
            try:
                message = decode_from_worker(await child.receive(MAX_FRAME))
            except (trio.BrokenResourceError, trio.ClosedResourceError):
                self._failed(arm, f"{self.settings.path}: {await child.gone()}")
                return
            except FrameError as exc:
                self._failed(arm, f"{self.settings.path}: the worker sent a bad frame: {exc}")
                return
            if isinstance(message, Line):
                await self._line(message)
            elif isinstance(message, Finished):
                self.outcome = ""
                log.info("%s finished", self.identity)
                return
            elif isinstance(message, Failed):
                where = f"{message.file}, line {message.line}" if message.line else message.file
                self._failed(arm, f"{where}: {message.error}: {message.message}")
                if message.traceback:
                    log.warning("%s:\n%s", self.identity, message.traceback)
                return
            else:
                answer = await self._answer(arm, message)
                try:
                    await child.send(encode(answer))
                except (trio.BrokenResourceError, trio.ClosedResourceError):
                    self._failed(arm, f"{self.settings.path}: {await child.gone()}")
                    return

    def _failed(self, arm: ScriptArm, sentence: str) -> None:
        self.outcome = sentence
        log.warning("%s: %s", self.identity, sentence)
        arm.fault(self.identity, ErrorCode.SCRIPT_FAILED, sentence, Severity.ERROR)

    async def _line(self, line: Line) -> None:
        """Log an output line, slowing the script once it writes faster than the bound (the
        pipe fills and its print waits)."""
        now = trio.current_time()
        self._line_tokens = min(
            float(self.settings.lines_burst),
            self._line_tokens + (now - self._line_time) * self.settings.lines_rate,
        )
        self._line_time = now
        if self._line_tokens < 1:
            await trio.sleep((1 - self._line_tokens) / self.settings.lines_rate)
            self._line_tokens, self._line_time = 1.0, trio.current_time()
        self._line_tokens -= 1
        self.counters.lines += 1
        self.lines.append(line.text)
        log.info("%s %s: %s", self.identity, line.stream, line.text)

    async def _answer(self, arm: ScriptArm, request: Request) -> Answer:
        """Carry out one request, paced at `rate`; a refusal is the answer, not an end."""
        await trio.sleep_until(self._next_request)
        self._next_request = max(self._next_request, trio.current_time()) + 1 / self.settings.rate
        self.counters.requests += 1
        try:
            value = await self._carry_out(arm, request)
        except ArenaError as error:
            self.counters.refused += 1
            return Answer(False, code=str(error.code), message=error.message)
        return Answer(True, value)

    async def _carry_out(self, arm: ScriptArm, request: Request) -> Any:
        if isinstance(request, Read):
            return self._read(arm, request.what)
        if isinstance(request, Wait):
            await self._wait(arm, request.seconds)
            return None
        if isinstance(request, MoveJoints | Gripper):
            if isinstance(request, MoveJoints):
                command = self._joint_command(request.joints, request.duration)
            else:
                goal = {self._gripper_name(): self._gripper(request.value)}
                command = self._joint_command(goal)
            targets = {goal.name: goal.value for goal in command.joints}

            async def send() -> Sent:
                return await arm.command(command), targets

        elif isinstance(request, PlannedJoints) or request.plan:
            plan = request

            async def send() -> Sent:
                return await arm.planned(plan, self.identity)

        else:
            data = pose_data(request)

            async def send() -> Sent:
                return await arm.pose(data, self.identity)

        milliseconds = request.duration if isinstance(request, MoveJoints | MoveToPose) else None
        seconds = None if milliseconds is None else milliseconds / 1000.0
        await self._move(arm, lambda: self._paced(arm, send), request.wait, seconds)
        return None

    # -- commands --------------------------------------------------------------------------------

    def _joint_command(self, joints: Mapping[str, float], duration: float | None = None) -> Command:
        if not joints:
            raise ArenaError(ErrorCode.EMPTY_COMMAND, "Name at least one joint to move.")
        for name, value in joints.items():
            if not math.isfinite(value):
                raise ArenaError(ErrorCode.INVALID_VALUE, f"Joint {name!r}: {value} is not finite.")
        if duration is not None and not 0 <= duration <= 3_600_000:
            raise ArenaError(ErrorCode.INVALID_VALUE, "`duration` must be 0 to 3600 s.")
        goals = tuple(wire.JointValue(name, value) for name, value in joints.items())
        seconds = None if duration is None else duration / 1000.0
        return Command(goals, seconds, self.identity)

    async def _paced(self, arm: ScriptArm, send: Callable[[], Awaitable[Sent]]) -> Sent:
        """`send()`, waiting through a pause (one that comes between the look and the command
        is refused MASTER_PAUSED: it waits and sends again)."""
        while True:
            if arm.paused:
                await arm.wait_resumed()
            result, targets = await send()
            if result.code is ErrorCode.MASTER_PAUSED:
                continue
            return result, targets

    async def _move(
        self,
        arm: ScriptArm,
        send: Callable[[], Awaitable[Sent]],
        wait: bool,
        duration: float | None,
    ) -> None:
        """Send a move; with `wait`, return once it is over; a pause meanwhile holds the arm,
        and the move is sent again on the resume."""
        pauses, stops = arm.pauses, arm.stops
        result, targets = await send()
        self._accepted(result)
        if not wait:
            return
        ending = MoveEnd(targets, duration, trio.current_time(), self._clamped)
        while True:
            await trio.sleep(POLL)
            # Paused since the move went (now, or a pause already over: the arm held where it
            # found it either way): sent again once resumed.
            if arm.paused or arm.pauses != pauses:
                await arm.wait_resumed()
                self.counters.pauses += 1
                pauses = arm.pauses
                result, targets = await send()
                self._accepted(result)
                ending = MoveEnd(targets, duration, trio.current_time(), self._clamped)
                continue
            if arm.stops != stops:  # held short of its goal: the script is told, not left
                raise ArenaError(ErrorCode.COLLISION, arm.last_stop)  # to think it arrived
            commanded, _ = arm.joint_values()
            if ending.over(commanded, trio.current_time()):
                return

    def _accepted(self, result: CommandResult) -> None:
        if not result.accepted:
            assert result.code is not None
            raise ArenaError(result.code, result.message)
        self.counters.commands += 1

    def _clamped(self, name: str, value: float) -> float:
        joint = self.model.joint(name)
        return value if joint is None else joint.clamp(value)

    def _gripper_name(self) -> str:
        hand = hand_for(self.model)
        joint = hand.gripper if hand is not None else self.model.joint("gripper")
        if joint is None:
            raise ArenaError(
                ErrorCode.INVALID_CONFIG,
                f"Robot type {self.model.robot_type!r} names no gripper joint.",
            )
        return joint.name

    def _gripper(self, value: float | str) -> float:
        joint = self.model.joint(self._gripper_name())
        assert joint is not None
        if value == "open":
            return joint.upper
        if value == "close":
            return joint.lower
        if isinstance(value, str):
            raise ArenaError(
                ErrorCode.INVALID_VALUE, f"Gripper {value!r}: open, close or a number."
            )
        return value

    # -- waits and reads -------------------------------------------------------------------------

    async def _wait(self, arm: ScriptArm, seconds: float) -> None:
        """Sleep `seconds` of time the script is not paused."""
        if not (math.isfinite(seconds) and 0 <= seconds <= 3600):
            raise ArenaError(ErrorCode.INVALID_VALUE, "A wait is 0 to 3600 s.")
        left = seconds
        while left > 0:
            if arm.paused:
                await arm.wait_resumed()
            start = trio.current_time()
            await trio.sleep(min(left, POLL * 5))
            if not arm.paused:
                left -= trio.current_time() - start

    def _read(self, arm: ScriptArm, what: str) -> Any:
        if what == "paused":
            return arm.paused
        commanded, measured = arm.joint_values()
        values = {name: measured.get(name, value) for name, value in commanded.items()}
        if what == "joints":
            return values
        if what == "pose":
            hand = hand_for(self.model)
            if hand is None:
                raise ArenaError(
                    ErrorCode.INVALID_CONFIG,
                    f"Robot type {self.model.robot_type!r} names no [end_effector]: no pose.",
                )
            pose = hand.pose(values)
            if pose is None:
                raise ArenaError(ErrorCode.INVALID_VALUE, "The hand's joints are not known yet.")
            return {
                "position": list(pose.position),
                "orientation": list(pose.orientation),
                "gripper": pose.gripper,
            }
        raise ArenaError(ErrorCode.INVALID_VALUE, f"Nothing called {what!r} to read.")


def pose_data(request: MoveToPose) -> wire.PoseData:
    """The request as the `pose` message's data, its bounds checked (INVALID_VALUE)."""
    fields: dict[str, Any] = {"position": list(request.position)}
    if request.orientation is not None:
        fields["orientation"] = list(request.orientation)
    if request.gripper is not None:
        fields["gripper"] = request.gripper
    if request.duration is not None:
        fields["duration"] = request.duration
    try:
        return msgspec.convert(fields, wire.PoseData)
    except msgspec.ValidationError as exc:
        raise ArenaError(ErrorCode.INVALID_VALUE, f"A pose: {exc}.") from None
