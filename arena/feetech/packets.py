"""The Feetech (SCS/STS) packet format, without I/O.

Instruction: `FF FF id len instr params... chk`; status: `FF FF id len err data... chk`, with
`len = params + 2` and `chk = ~(id + len + instr/err + sum(params)) & 0xFF`. The parser takes
bytes as they arrive and yields whole packets, resynchronising on the next header after noise
or a bad checksum.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

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


class PacketParser:
    """Incremental parser: `feed(data)` returns the packets (and corrupt frames) completed."""

    def __init__(self) -> None:
        self._buffer = bytearray()

    def feed(self, data: bytes) -> list[Packet | Corrupt]:
        """Add received bytes; return every frame they complete, in order."""
        self._buffer += data
        found: list[Packet | Corrupt] = []
        buffer = self._buffer
        while True:
            start = buffer.find(HEADER)
            if start < 0:
                # Keep a trailing 0xFF: it may be the first half of the next header.
                del buffer[: len(buffer) - 1 if buffer.endswith(b"\xff") else len(buffer)]
                return found
            del buffer[:start]
            if len(buffer) < 4:
                return found
            servo_id, length = buffer[2], buffer[3]
            if servo_id == 0xFF or length < 2 or length > MAX_LENGTH:
                del buffer[:1]  # not a real header (FF FF FF ...): slide by one
                continue
            end = 4 + length
            if len(buffer) < end:
                return found
            frame = bytes(buffer[:end])
            del buffer[:end]
            body = frame[2:-1]
            if checksum(body) != frame[-1]:
                found.append(Corrupt(servo_id, frame))
            else:
                found.append(Packet(servo_id, body[2], body[3:]))

    def clear(self) -> None:
        """Drop any partial frame."""
        self._buffer.clear()
