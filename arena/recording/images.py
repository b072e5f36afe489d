"""Camera frames in recordings: Foxglove's `CompressedImage` on `/robots/{id}/cameras/{name}`.

Frames are written by the recording process with the SDK's encoder, so Foxglove shows them as
they are; reading them back for `arena export` takes a small decoder of the four fields that
message has, which spares export loading protobuf's runtime for every frame.
"""

from __future__ import annotations

from dataclasses import dataclass

from foxglove.messages import CompressedImage, Timestamp

from arena.robot.events import CameraFrame


def schema() -> tuple[str, str, bytes]:
    """(name, encoding, data) of Foxglove's CompressedImage schema."""
    found = CompressedImage.get_schema()
    return found.name, found.encoding, bytes(found.data)


def encode(frame: CameraFrame, log_time: int) -> bytes:
    """A frame as Foxglove's CompressedImage, stamped with its capture time (`log_time`)."""
    return CompressedImage(
        timestamp=Timestamp(log_time // 1_000_000_000, log_time % 1_000_000_000),
        frame_id=f"{frame.robot_id}/cameras/{frame.camera}",
        data=frame.jpeg,
        format="jpeg",
    ).encode()


@dataclass(frozen=True, slots=True)
class Image:
    """A CompressedImage read back."""

    stamp: int  # ns since the epoch
    frame_id: str
    format: str
    data: bytes


def _varint(data: bytes, at: int) -> tuple[int, int]:
    value, shift = 0, 0
    while True:
        if at >= len(data):
            raise ValueError("message cut inside a varint")
        byte = data[at]
        at += 1
        value |= (byte & 0x7F) << shift
        if byte < 0x80:
            return value, at
        shift += 7
        if shift > 63:
            raise ValueError("varint too long")


def _fields(data: bytes) -> dict[int, int | bytes]:
    """Field number -> value of a protobuf message (varints and length-delimited fields; the
    last occurrence wins, as protobuf says)."""
    found: dict[int, int | bytes] = {}
    at = 0
    while at < len(data):
        key, at = _varint(data, at)
        number, wire = key >> 3, key & 7
        if wire == 0:
            found[number], at = _varint(data, at)
        elif wire == 2:
            length, at = _varint(data, at)
            if at + length > len(data):
                raise ValueError("field runs past the message")
            found[number] = data[at : at + length]
            at += length
        elif wire == 1:
            at += 8
        elif wire == 5:
            at += 4
        else:
            raise ValueError(f"unsupported wire type {wire}")
    return found


def _number(value: int | bytes) -> int:
    if not isinstance(value, int):
        raise ValueError("a number field holds bytes")
    return value


def decode(data: bytes) -> Image:
    """A CompressedImage message; `ValueError` if it is not one."""
    fields = _fields(data)
    stamp = fields.get(1, b"")
    seconds = nanos = 0
    if isinstance(stamp, bytes) and stamp:
        parts = _fields(stamp)
        seconds, nanos = _number(parts.get(1, 0)), _number(parts.get(2, 0))
    payload, kind, frame_id = fields.get(2, b""), fields.get(3, b""), fields.get(4, b"")
    if not isinstance(payload, bytes) or not isinstance(kind, bytes):
        raise ValueError("not a CompressedImage")
    return Image(
        seconds * 1_000_000_000 + nanos,
        frame_id.decode() if isinstance(frame_id, bytes) else "",
        kind.decode(),
        payload,
    )
