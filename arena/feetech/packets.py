"""The Feetech (SCS/STS) packet format, without I/O.

Instruction: `FF FF id len instr params... chk`; status: `FF FF id len err data... chk`, with
`len = params + 2` and `chk = ~(id + len + instr/err + sum(params)) & 0xFF`. The parser takes
bytes as they arrive and yields whole packets, resynchronising on the next header after noise
or a bad checksum.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

from arena.servo.frames import FrameParser

HEADER = b"\xff\xff"
MAX_LENGTH = 250  # largest `len` field a packet may carry


class Instruction(enum.IntEnum):
    """Instruction codes."""

    PING = 0x01
    READ = 0x02
    WRITE = 0x03
    REG_WRITE = 0x04
    ACTION = 0x05
    SYNC_READ = 0x82
    SYNC_WRITE = 0x83


@dataclass(frozen=True, slots=True)
class Packet:
    """One packet: `code` is the instruction (to servos) or the error byte (from a servo)."""

    servo_id: int
    code: int
    params: bytes


@dataclass(frozen=True, slots=True)
class Corrupt:
    """A frame whose checksum did not match (it is dropped)."""

    servo_id: int
    raw: bytes


def checksum(body: bytes) -> int:
    """The checksum of the bytes between the header and the checksum byte."""
    return ~sum(body) & 0xFF


def encode(servo_id: int, code: int, params: bytes = b"") -> bytes:
    """One packet's bytes."""
    if not 0 <= servo_id <= 0xFE:
        raise ValueError(f"servo id {servo_id} is outside 0..254")
    if len(params) + 2 > MAX_LENGTH:
        raise ValueError(f"{len(params)} parameter bytes do not fit in one packet")
    body = bytes((servo_id, len(params) + 2, code)) + params
    return HEADER + body + bytes((checksum(body),))


class PacketParser(FrameParser[Packet | Corrupt]):
    """Incremental parser: `feed(data)` returns the packets (and corrupt frames) completed."""

    HEADER = HEADER
    HEAD_SIZE = 4  # FF FF, id, length

    def _frame_size(self, head: bytes) -> int | None:
        servo_id, length = head[2], head[3]
        if servo_id == 0xFF or length < 2 or length > MAX_LENGTH:
            return None  # (FF FF FF ...)
        return 4 + length

    def _decode(self, frame: bytes) -> Packet | Corrupt:
        body = frame[2:-1]
        if checksum(body) != frame[-1]:
            return Corrupt(frame[2], frame)
        return Packet(frame[2], body[2], body[3:])
