"""The pipe between Arena and a script's worker: length-prefixed msgpack frames of typed
messages (as a policy's, `arena.policy.wire`). The worker asks, one request at a time, and
waits for the answer; it also tells its output lines and how the script ended. Nothing on the
pipe is pickled: a frame that is not one of these structs, or longer than `MAX_FRAME`, ends the
conversation (the worker is killed).
"""

from __future__ import annotations

from typing import Any, TypeAlias

import msgspec

from arena.protocol import frames
from arena.protocol.frames import HEADER as HEADER
from arena.protocol.frames import FrameError as FrameError

#: The largest frame either side accepts (a request names a few joints; a line is bounded).
MAX_FRAME = 64 * 1024
#: The longest output line kept (characters; the rest is cut and marked).
MAX_LINE = 1000


class MoveJoints(msgspec.Struct, tag="move_joints", frozen=True):
    """Command these joints (degrees, or the gripper's unit) over `duration` ms (None: as
    fast as the limits allow); with `wait`, answer once the move is done."""

    joints: dict[str, float]
    duration: float | None = None
    wait: bool = True


class MoveToPose(msgspec.Struct, tag="move_to_pose", frozen=True):
    """Move the hand's tool point to `position` (metres, the base frame), turned to
    `orientation` (x, y, z, w) if given; with `plan`, along a planned path."""

    position: tuple[float, float, float]
    orientation: tuple[float, float, float, float] | None = None
    gripper: float | None = None
    duration: float | None = None
    wait: bool = True
    plan: bool = False


class PlannedJoints(msgspec.Struct, tag="plan_joints", frozen=True):
    """Move the joints to `joints` along a planned path (free of collisions)."""

    joints: dict[str, float]
    wait: bool = True


class Gripper(msgspec.Struct, tag="gripper", frozen=True):
    """Set the gripper's joint to `value` (its unit)."""

    value: float | str  # a number, "open" or "close"
    wait: bool = True


class Wait(msgspec.Struct, tag="wait", frozen=True):
    """Answer after `seconds` (the robot's clock; a pause does not count)."""

    seconds: float


class Read(msgspec.Struct, tag="read", frozen=True):
    """Answer with `what`: `joints` ({name: value}), `pose` (the measured pose, else the
    commanded one), `paused` (bool)."""

    what: str


class Line(msgspec.Struct, tag="line", frozen=True):
    """A line the script wrote (print, a warning, its log); not answered."""

    text: str
    stream: str = "stdout"


class Finished(msgspec.Struct, tag="finished", frozen=True):
    """The script ended without an error; not answered (the worker exits)."""


class Failed(msgspec.Struct, tag="failed", frozen=True):
    """The script raised: the exception's type and message, and the script's file and line
    where it was raised (its deepest frame in the script); not answered."""

    error: str
    message: str
    file: str
    line: int
    traceback: str = ""


class Answer(msgspec.Struct, tag="answer", frozen=True):
    """A request's answer: `value` when done, else the refusal's code and sentence."""

    ok: bool
    value: Any = None
    code: str = ""
    message: str = ""


Request: TypeAlias = MoveJoints | MoveToPose | PlannedJoints | Gripper | Wait | Read
FromWorker: TypeAlias = Request | Line | Finished | Failed

_to_parent = msgspec.msgpack.Decoder(FromWorker)
_to_worker = msgspec.msgpack.Decoder(Answer)
_encoder = msgspec.msgpack.Encoder()


def encode(message: FromWorker | Answer) -> bytes:
    """One message as a frame."""
    return frames.pack(_encoder.encode(message), MAX_FRAME)


def decode_from_worker(body: bytes) -> FromWorker:
    """A frame's body from the worker; `FrameError` if it is none of its messages."""
    try:
        message: FromWorker = _to_parent.decode(body)
    except msgspec.DecodeError as exc:
        raise FrameError(f"not a message of a script's worker: {exc}") from None
    return message


def decode_answer(body: bytes) -> Answer:
    """A frame's body from the parent; `FrameError` if it is not an answer."""
    try:
        return _to_worker.decode(body)
    except msgspec.DecodeError as exc:
        raise FrameError(f"not an answer: {exc}") from None
