"""Movement sequences: keyframes in the wire's `sequence` format, and the built-in demos.

A sequence is data: `{"id", "name", "commands": [{"timestamp" (ms), "joints", "duration" (ms)}],
"total_duration" (ms), "loop"}`. The demo sequences live as JSON files beside this module.
"""

from __future__ import annotations

import functools
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeGuard

from arena.protocol.errors import ArenaError, ErrorCode
from arena.robot.model import RobotModel
from arena.robot.motion import Command, JointGoal, resolve_command

DEMO_DIR = Path(__file__).resolve().parent / "sequences"


@dataclass(frozen=True, slots=True)
class Keyframe:
    """A command issued `at` seconds after the sequence starts."""

    at: float
    command: Command


@dataclass(frozen=True, slots=True)
class Sequence:
    """A named, timed list of commands."""

    id: str
    name: str
    keyframes: tuple[Keyframe, ...]
    total_duration: float  # seconds
    loop: bool = False
    description: str = ""

    def check_against(self, model: RobotModel) -> None:
        """Raise `ArenaError` if any keyframe names an unknown joint or bad value: a sequence
        written for one robot type is refused before it plays on another."""
        for keyframe in self.keyframes:
            try:
                resolve_command(model, keyframe.command)
            except ArenaError as error:
                raise ArenaError(
                    error.code,
                    f"Sequence '{self.id}' does not fit a {model.robot_type}: {error.message}",
                ) from None

    def summary(self) -> dict[str, Any]:
        """Id, name, description and duration (ms), as the sequence listing shows them."""
        return {
            "id": self.id,
            "name": self.name,
            "description": self.description,
            "duration": round(self.total_duration * 1000),
            "loop": self.loop,
        }


def parse_sequence(data: Any) -> Sequence:
    """Build a sequence from its wire form, raising `ArenaError(INVALID_VALUE)` when malformed."""

    def bad(why: str) -> ArenaError:
        return ArenaError(ErrorCode.INVALID_VALUE, f"Invalid sequence: {why}")

    if not isinstance(data, dict):
        raise bad("expected an object")
    commands = data.get("commands")
    if not isinstance(commands, list) or not commands:
        raise bad("'commands' must be a non-empty list")
    keyframes: list[Keyframe] = []
    last = 0.0
    for index, entry in enumerate(commands):
        where = f"commands[{index}]"
        if not isinstance(entry, dict):
            raise bad(f"{where} must be an object")
        at = _milliseconds(entry.get("timestamp", 0), f"{where}.timestamp", bad)
        if at < last:
            raise bad(f"{where}.timestamp goes back in time")
        last = at
        duration = entry.get("duration")
        seconds = None if duration is None else _milliseconds(duration, f"{where}.duration", bad)
        joints = entry.get("joints")
        if not isinstance(joints, list) or not joints:
            raise bad(f"{where}.joints must be a non-empty list")
        goals = []
        for joint in joints:
            if not isinstance(joint, dict) or not isinstance(joint.get("name"), str):
                raise bad(f"{where}.joints entries need a 'name'")
            value, speed = joint.get("value"), joint.get("speed")
            if not _finite(value) or (speed is not None and not _finite(speed)):
                raise bad(f"{where}: joint {joint['name']!r} needs a finite value")
            goals.append(
                JointGoal(joint["name"], float(value), None if speed is None else float(speed))
            )
        keyframes.append(Keyframe(at, Command(tuple(goals), seconds, "sequence")))
    ends = max(k.at + (k.command.duration or 0.0) for k in keyframes)
    total = data.get("total_duration")
    total_s = ends if total is None else _milliseconds(total, "total_duration", bad)
    if total_s < keyframes[-1].at:
        raise bad("total_duration ends before the last command")
    loop = bool(data.get("loop", False))
    if loop and total_s <= 0:
        raise bad(
            "a looping sequence needs a duration above zero (a total_duration, or commands "
            "at different timestamps): one of no duration would repeat without pause"
        )
    return Sequence(
        id=str(data.get("id", "custom")),
        name=str(data.get("name", data.get("id", "custom"))),
        keyframes=tuple(keyframes),
        total_duration=total_s,
        loop=loop,
        description=str(data.get("description", "")),
    )


def _finite(value: Any) -> TypeGuard[int | float]:
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


def _milliseconds(value: Any, field: str, bad: Any) -> float:
    if not _finite(value) or value < 0:
        raise bad(f"{field} must be a number of milliseconds >= 0")
    return float(value) / 1000.0


@functools.cache
def demo_sequences() -> dict[str, Sequence]:
    """The built-in demo sequences by id."""
    found = {}
    for path in sorted(DEMO_DIR.glob("*.json")):
        sequence = parse_sequence(json.loads(path.read_text(encoding="utf-8")))
        found[sequence.id] = sequence
    return found


def get_sequence(sequence_id: str) -> Sequence:
    """A demo sequence by id; raises `ArenaError(UNKNOWN_SEQUENCE)`."""
    sequences = demo_sequences()
    if sequence_id not in sequences:
        known = ", ".join(sequences)
        raise ArenaError(
            ErrorCode.UNKNOWN_SEQUENCE, f"No sequence {sequence_id!r}; available: {known}."
        )
    return sequences[sequence_id]
