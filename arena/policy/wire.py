"""The pipe between Arena and a policy worker: length-prefixed msgpack frames of typed messages.

Nothing on this pipe is pickled. Each frame is a 4-byte big-endian length and a msgpack body
that msgspec decodes into one of the structs below and nothing else: a frame that is not one of
them, or longer than `MAX_FRAME`, is an error, never code that runs. Images travel as the JPEG
bytes the camera captured (the worker decodes them, so the server spends no time on pixels).
"""

from __future__ import annotations

from typing import TypeAlias

import msgspec

from arena.protocol import frames
from arena.protocol.frames import HEADER as HEADER  # the worker and the server read it
from arena.protocol.frames import FrameError as FrameError

#: The largest frame either side accepts: four 1080p JPEGs with room to spare.
MAX_FRAME = 32 * 1024 * 1024


class Load(msgspec.Struct, tag="load", frozen=True):
    """Load the policy saved in `path` (a LeRobot 0.4 directory)."""

    path: str


class Feature(msgspec.Struct, frozen=True):
    """One of the policy's input or output features, as its `config.json` declares it."""

    name: str
    kind: str  # LeRobot's FeatureType: STATE, VISUAL, ENV, ACTION, ...
    shape: tuple[int, ...]


class Loaded(msgspec.Struct, tag="loaded", frozen=True):
    """The policy is loaded: its type, checkpoint (first 12 hex digits of the SHA-256 of its
    `model.safetensors`), features and chunk length (`chunk_size`: actions one inference
    gives)."""

    policy_type: str
    checkpoint: str
    inputs: tuple[Feature, ...]
    outputs: tuple[Feature, ...]
    chunk_size: int
    seconds: float  # how long the load took
    lerobot: str = ""  # the version of LeRobot the worker runs
    python: str = ""  # ...and of its Python


class Observe(msgspec.Struct, tag="observe", frozen=True):
    """One observation: `observation.state` in LeRobot's units, JPEG frames by camera name,
    the task, and `observation.environment_state` (empty: none). `timestep` is the control
    step it was taken at; the chunk answers with it."""

    timestep: int
    state: tuple[float, ...]
    images: dict[str, bytes]
    task: str
    environment_state: tuple[float, ...] = ()


class Chunk(msgspec.Struct, tag="chunk", frozen=True):
    """The actions for `timestep`, `timestep + 1`, ... in LeRobot's units; `latency`: seconds
    from the observation's arrival to the answer (decode, preprocess, inference,
    postprocess)."""

    timestep: int
    actions: tuple[tuple[float, ...], ...]
    latency: float


class Failed(msgspec.Struct, tag="failed", frozen=True):
    """The request could not be carried out; `reason` says why in a sentence."""

    reason: str


ToWorker: TypeAlias = Load | Observe
FromWorker: TypeAlias = Loaded | Chunk | Failed

_encoder = msgspec.msgpack.Encoder()
_to_worker = msgspec.msgpack.Decoder(ToWorker)
_from_worker = msgspec.msgpack.Decoder(FromWorker)


def encode(message: ToWorker | FromWorker) -> bytes:
    """`message` as one frame: its length, then its msgpack body."""
    return frames.pack(_encoder.encode(message), MAX_FRAME)


def frame_length(header: bytes) -> int:
    """The body length a frame's 4-byte header announces; `FrameError` past `MAX_FRAME`."""
    return frames.frame_length(header, MAX_FRAME)


def decode_to_worker(body: bytes) -> ToWorker:
    """A request to the worker from a frame's body."""
    try:
        request: ToWorker = _to_worker.decode(body)
    except msgspec.DecodeError as exc:
        raise FrameError(f"not a request to a policy worker: {exc}") from None
    return request


def decode_from_worker(body: bytes) -> FromWorker:
    """A worker's answer from a frame's body."""
    try:
        answer: FromWorker = _from_worker.decode(body)
    except msgspec.DecodeError as exc:
        raise FrameError(f"not an answer of a policy worker: {exc}") from None
    return answer
