"""Replay: a recording's commands as a master, and a whole recorded session re-driven.

`ReplayMaster` issues one robot's accepted commands with their recorded timing (speed factor,
loop, time window) and obeys every master rule: it takes the robot over, is refused during an
e-stop, and an e-stop ends it for good. `redrive_session` feeds all of one robot's recorded
inputs (masters, commands, e-stops, resets) into another robot at their recorded times: the
basis of the deterministic replay tests.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass

import trio

from arena.protocol.errors import ArenaError, ErrorCode
from arena.recording.mcap_file import RecordedMessage, Recording
from arena.robot.handle import Robot
from arena.robot.links import RELEASED_HOLDING, MasterLink
from arena.robot.motion import Command, JointGoal

log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class TimedCommand:
    """A command `at` seconds after the first one."""

    at: float
    command: Command


def recorded_robots(recording: Recording) -> list[str]:
    """Ids of the robots in a recording, in order of first appearance."""
    return list(dict.fromkeys(m.robot_id for m in recording.messages))


def pick_robot(recording: Recording, robot_id: str | None, named: str = "--robot") -> str:
    """`robot_id`, or the only robot in the recording; a clear error otherwise, naming the
    option or field (`named`) by which the robot is chosen."""
    robots = recorded_robots(recording)
    if robot_id is None:
        if len(robots) == 1:
            return robots[0]
        raise ArenaError(
            ErrorCode.INVALID_VALUE,
            f"{recording.path.name} holds robots {robots}: say which with {named}.",
        )
    if robot_id not in robots:
        raise ArenaError(
            ErrorCode.UNKNOWN_ROBOT,
            f"{recording.path.name} has no robot {robot_id!r} ({named}); it has {robots}.",
        )
    return robot_id


def command_of(data: dict[str, object]) -> Command:
    """A recorded command record back into a `Command`."""
    joints = data["joints"]
    assert isinstance(joints, list)
    duration = data.get("duration")
    label = data.get("label")
    return Command(
        tuple(JointGoal(j["name"], j["value"], j.get("speed")) for j in joints),
        None if duration is None else float(duration) / 1000.0,  # type: ignore[arg-type]
        None if label is None else str(label),
    )


def recorded_commands(
    recording: Recording, robot_id: str, start: float | None = None, end: float | None = None
) -> list[TimedCommand]:
    """The accepted commands of `robot_id`, timed from the first one, within [start, end)."""
    accepted = [
        m
        for m in recording.messages
        if m.robot_id == robot_id and m.kind == "command" and m.data["accepted"]
    ]
    if not accepted:
        raise ArenaError(
            ErrorCode.INVALID_RECORDING,
            f"{recording.path.name} holds no accepted command of {robot_id!r}.",
        )
    origin = float(accepted[0].data["t"])
    timed = [TimedCommand(float(m.data["t"]) - origin, command_of(m.data)) for m in accepted]
    lower = start or 0.0
    window = [c for c in timed if c.at >= lower and (end is None or c.at < end)]
    return [TimedCommand(c.at - lower, c.command) for c in window]


class ReplayMaster:
    """Plays recorded commands onto a robot as its master."""

    kind = "replay"
    autonomous = True
    takes_over = False  # only when asked (`takeover`)

    def __init__(
        self,
        commands: list[TimedCommand],
        *,
        speed: float = 1.0,
        loop: bool = False,
        name: str = "replay",
    ) -> None:
        if not commands:
            raise ArenaError(ErrorCode.INVALID_RECORDING, "Nothing to replay.")
        if not 0.01 <= speed <= 1000:
            raise ArenaError(ErrorCode.INVALID_VALUE, "speed must be between 0.01 and 1000.")
        self.commands = commands
        self.speed = speed
        self.loop = loop
        self.name = name
        self.sent = 0
        self.refused = 0
        self.on_progress: Callable[[int, int], None] | None = None

    @property
    def description(self) -> str:
        """What it replays, in words (told to a master it takes over from, shown with the
        robot's master)."""
        return f"replay of {self.name!r}" + (" in a loop" if self.loop else "")

    async def run(self, link: MasterLink) -> None:
        """Issue every command at its (scaled) time; loop if asked."""
        while True:
            # The master's own clock: it stands still while the robot has it paused.
            start = trio.current_time() - link.paused_time(trio.current_time())
            for index, timed in enumerate(self.commands):
                await link.sleep_until(start + timed.at / self.speed)
                command = timed.command
                if command.duration is not None and self.speed != 1.0:
                    command = Command(command.joints, command.duration / self.speed, command.source)
                # Behind schedule (a fast replay), an idle robot decides at once; the
                # checkpoint keeps the replay from starving the robot's other work.
                result = link.command_now(command)
                if result is None:
                    result = await link.command(command)
                elif index % 16 == 15:
                    await trio.lowlevel.checkpoint()
                self.sent += 1
                if not result.accepted:
                    self.refused += 1
                    if result.code in (ErrorCode.ESTOPPED, ErrorCode.NOT_OWNER):
                        return  # stopped for good
                if self.on_progress is not None:
                    self.on_progress(index + 1, len(self.commands))
            if not self.loop:
                return


async def redrive_session(recording: Recording, source: str, robot: Robot) -> None:
    """Feed `source`'s recorded inputs into `robot` at their recorded relative times."""
    inputs = [m for m in recording.messages if m.robot_id == source and _is_input(m)]
    if not inputs:
        return
    origin = float(inputs[0].data["t"])
    start = trio.current_time()
    links: dict[str, MasterLink] = {}
    for message in inputs:
        await trio.sleep_until(start + float(message.data["t"]) - origin)
        data = message.data
        if message.kind == "peer":
            peer = str(data["peer_id"])
            if data["change"] == "attached":
                links[peer] = await robot.connect_master(
                    peer,
                    kind=str(data["kind"]),
                    takeover=True,
                    autonomous=bool(data.get("autonomous")),
                )
            elif peer in links and not links[peer].detached.is_set():
                if data["change"] == "lost":
                    await links[peer].lost(str(data["reason"]))
                elif data["change"] == "released":
                    hold = data["reason"] == RELEASED_HOLDING
                    await links[peer].release(str(data["reason"]), hold=hold)
                else:
                    finished = data["reason"] == "driver finished"  # see Robot._on_driver_ended
                    await links[peer].detach(str(data["reason"]), finish_motion=finished)
        elif message.kind == "command":
            source_id = str(data["source"])
            master = None if source_id == "manual" else links.get(source_id)
            await robot.command(
                command_of(data), master_id=None if master is None else master.master_id
            )
        elif data["cause"] == "EStop":
            await robot.estop(str(data["estop_reason"]))
        else:
            await robot.reset()


def _is_input(message: RecordedMessage) -> bool:
    data = message.data
    if message.kind == "command":
        return True
    if message.kind == "peer":
        return data["role"] == "master" and data["change"] in (
            "attached",
            "detached",
            "released",
            "lost",
        )
    return message.kind == "state" and data["cause"] in ("EStop", "Reset")
