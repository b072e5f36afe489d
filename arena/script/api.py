"""What a script calls to drive its robot (`from arena.script import move_to_pose, wait`).

Each call is a request to the robot's master (the server, or `arena script` on another machine)
and returns once it is answered: a move once the arm has got there (`wait=False`: once the
command was accepted), a read with its value. A command the robot refuses (a limit, the
collision guard, an e-stop) raises `ScriptError` with the robot's code and sentence; a script
that does not catch it ends there, reported as a fault with its line. While the robot has the
script paused every call waits for the resume. Outside a script's worker every call raises
`RuntimeError`.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Mapping, Sequence
from typing import Any, BinaryIO

from arena.protocol.frames import frame_length
from arena.script.wire import (
    HEADER,
    MAX_FRAME,
    Answer,
    FrameError,
    Gripper,
    MoveJoints,
    MoveToPose,
    PlannedJoints,
    Read,
    Request,
    Wait,
    decode_answer,
    encode,
)


class ScriptError(Exception):
    """The robot refused a request: `code` (ESTOPPED, COLLISION, UNREACHABLE, ...) and the
    robot's sentence."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(f"{code}: {message}")
        self.code = code
        self.message = message


class Channel:
    """The worker's end of the pipe: one request and its answer at a time (a lock: a script
    may call from threads of its own)."""

    def __init__(self, reader: BinaryIO, writer: BinaryIO) -> None:
        self.reader = reader
        self.writer = writer
        self.lock = threading.Lock()

    def tell(self, message: Any) -> None:
        """Send a message that is not answered (a line, how the script ended)."""
        with self.lock:
            self.writer.write(encode(message))
            self.writer.flush()

    def ask(self, request: Request) -> Answer:
        """Send `request`, wait for its answer."""
        with self.lock:
            self.writer.write(encode(request))
            self.writer.flush()
            return decode_answer(self._exactly(frame_length(self._exactly(HEADER.size), MAX_FRAME)))

    def _exactly(self, count: int) -> bytes:
        data = b""
        while len(data) < count:
            chunk = self.reader.read(count - len(data))
            if not chunk:
                raise FrameError("the robot's master closed the pipe")
            data += chunk
        return data


_state: dict[str, Channel] = {}


def connect(channel: Channel) -> None:
    """Make `channel` the one every call of this module goes through (the worker does)."""
    _state["channel"] = channel


def _call(request: Request) -> Any:
    channel = _state.get("channel")
    if channel is None:
        raise RuntimeError(
            "arena.script drives a robot only inside a script run by Arena: "
            "POST /api/robots/{id}/master with type script, or `arena script FILE --url URL "
            "--robot ID`."
        )
    answer = channel.ask(request)
    if not answer.ok:
        raise ScriptError(answer.code, answer.message)
    return answer.value


def _number(name: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise ValueError(f"{name}: {value!r} is not a finite number")
    return float(value)


def _milliseconds(duration: float | None) -> float | None:
    return None if duration is None else _number("duration", duration) * 1000.0


def move_joints(
    joints: Mapping[str, float], *, duration: float | None = None, wait: bool = True
) -> None:
    """Move the named joints to these values (degrees; the gripper in its unit) over
    `duration` seconds (None: as fast as the joints' limits allow)."""
    values = {str(name): _number(f"joint {name!r}", value) for name, value in joints.items()}
    _call(MoveJoints(values, _milliseconds(duration), wait))


def move_to_pose(
    position: Sequence[float],
    orientation: Sequence[float] | None = None,
    *,
    gripper: float | None = None,
    duration: float | None = None,
    wait: bool = True,
) -> None:
    """Move the hand's tool point to `position` (x, y, z metres in the robot's base frame),
    turned to `orientation` (a quaternion x, y, z, w) if given; the joints are solved by
    inverse kinematics (`ScriptError` UNREACHABLE when no pose of the arm gets there)."""
    x, y, z = (_number("position", v) for v in position)
    turned = None
    if orientation is not None:
        qx, qy, qz, qw = (_number("orientation", v) for v in orientation)
        turned = (qx, qy, qz, qw)
    grip = None if gripper is None else _number("gripper", gripper)
    _call(MoveToPose((x, y, z), turned, grip, _milliseconds(duration), wait))


def move(
    joints: Mapping[str, float] | None = None,
    *,
    position: Sequence[float] | None = None,
    orientation: Sequence[float] | None = None,
    plan: bool = False,
    wait: bool = True,
) -> None:
    """Move to a joint goal or a pose (one of them); `plan=True` takes a path planned around
    the table, the keep-out boxes and the arm itself, where the server plans moves (else
    `ScriptError` NOT_INSTALLED saying so); `plan=False` is `move_joints` or `move_to_pose`."""
    if (joints is None) == (position is None):
        raise ValueError("move: give either joints or a position")
    if joints is not None:
        if not plan:
            move_joints(joints, wait=wait)
            return
        values = {str(n): _number(f"joint {n!r}", v) for n, v in joints.items()}
        _call(PlannedJoints(values, wait))
        return
    assert position is not None
    x, y, z = (_number("position", v) for v in position)
    turned = None
    if orientation is not None:
        qx, qy, qz, qw = (_number("orientation", v) for v in orientation)
        turned = (qx, qy, qz, qw)
    _call(MoveToPose((x, y, z), turned, None, None, wait, plan))


def gripper(value: float | str, *, wait: bool = True) -> None:
    """Open (`"open"`: the top of the gripper joint's range), close (`"close"`: its bottom)
    or set the gripper to `value` (its unit: percent on the so-arms)."""
    if isinstance(value, str):
        if value not in ("open", "close"):
            raise ValueError(f'gripper: {value!r} is neither "open", "close" nor a number')
        _call(Gripper(value, wait))
        return
    _call(Gripper(_number("gripper", value), wait))


def wait(seconds: float) -> None:
    """Wait `seconds` (at most an hour) on the robot's clock; time paused does not count."""
    seconds = _number("seconds", seconds)
    if not 0 <= seconds <= 3600:
        raise ValueError(f"wait: {seconds} s is not between 0 and 3600")
    _call(Wait(seconds))


def joints() -> dict[str, float]:
    """Each joint's measured value (its commanded one until the arm reports it), by name."""
    value: dict[str, float] = _call(Read("joints"))
    return value


def pose() -> dict[str, Any]:
    """The hand's pose: `position` (m), `orientation` (x, y, z, w), `gripper`; measured, else
    commanded."""
    value: dict[str, Any] = _call(Read("pose"))
    return value


def paused() -> bool:
    """Whether the robot has the script paused now (every call waits through a pause by
    itself: this is for a script that wants to know)."""
    return bool(_call(Read("paused")))
