"""The Dynamixel Protocol 2.0 packet format, without I/O.

Instruction: `FF FF FD 00 id len_l len_h instr params... crc_l crc_h`; status: the same with
instruction 0x55, then the error byte and the data. `len` counts instruction, parameters and
CRC. The CRC is CRC-16 with polynomial 0x8005 (initial 0, not reflected) over every byte before
it. Inside instruction and parameters, `FF FF FD` is followed by a stuffing `FD` so that no
header appears in a packet's body. The parser takes bytes as they arrive and yields whole
packets, resynchronising on the next header after noise or a bad CRC.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

from arena.servo.frames import FrameParser

HEADER = b"\xff\xff\xfd\x00"
STATUS = 0x55
MAX_LENGTH = 1024  # largest `len` field accepted


class Instruction(enum.IntEnum):
    """Instruction codes."""

    PING = 0x01
    READ = 0x02
    WRITE = 0x03
    REG_WRITE = 0x04
    ACTION = 0x05
    FACTORY_RESET = 0x06
    REBOOT = 0x08
    SYNC_READ = 0x82
    SYNC_WRITE = 0x83
    BULK_READ = 0x92
    BULK_WRITE = 0x93


class StatusError(enum.IntEnum):
    """A status packet's error number (its low 7 bits); bit 7 is the hardware alert."""

    NONE = 0
    RESULT_FAIL = 1
    INSTRUCTION = 2
    CRC = 3
    DATA_RANGE = 4
    DATA_LENGTH = 5
    DATA_LIMIT = 6
    ACCESS = 7


ALERT = 0x80


@dataclass(frozen=True, slots=True)
class Packet:
    """One packet, unstuffed: `instruction` (0x55 for a status packet), then for a status
    packet `error` and its data in `params`."""

    servo_id: int
    instruction: int
    params: bytes
    error: int = 0


@dataclass(frozen=True, slots=True)
class Corrupt:
    """A frame whose CRC did not match (it is dropped)."""

    servo_id: int
    raw: bytes


def _crc_table() -> tuple[int, ...]:
    table = []
    for byte in range(256):
        crc = byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x8005) if crc & 0x8000 else crc << 1
        table.append(crc & 0xFFFF)
    return tuple(table)


_TABLE = _crc_table()


def crc16(data: bytes) -> int:
    """Protocol 2.0's CRC of `data`."""
    crc = 0
    for byte in data:
        crc = ((crc << 8) ^ _TABLE[((crc >> 8) ^ byte) & 0xFF]) & 0xFFFF
    return crc


def stuff(body: bytes) -> bytes:
    """`body` with an `FD` after every `FF FF FD`."""
    out = bytearray()
    for byte in body:
        out.append(byte)
        if out[-3:] == b"\xff\xff\xfd":
            out.append(0xFD)
    return bytes(out)


def unstuff(body: bytes) -> bytes:
    """`body` without the stuffing `FD`s."""
    out = bytearray()
    i = 0
    while i < len(body):
        out.append(body[i])
        if out[-3:] == b"\xff\xff\xfd" and body[i + 1 : i + 2] == b"\xfd":
            i += 1  # the stuffing byte
        i += 1
    return bytes(out)


def encode(servo_id: int, instruction: int, params: bytes = b"") -> bytes:
    """One instruction packet's bytes."""
    return _frame(servo_id, bytes((instruction,)) + params)


def encode_status(servo_id: int, error: int, data: bytes = b"") -> bytes:
    """One status packet's bytes."""
    return _frame(servo_id, bytes((STATUS, error)) + data)


def _frame(servo_id: int, body: bytes) -> bytes:
    if not 0 <= servo_id <= 0xFE:
        raise ValueError(f"servo id {servo_id} is outside 0..254")
    stuffed = stuff(body)
    length = len(stuffed) + 2
    if length > MAX_LENGTH:
        raise ValueError(f"{len(body)} bytes do not fit in one packet")
    head = HEADER + bytes((servo_id,)) + length.to_bytes(2, "little") + stuffed
    return head + crc16(head).to_bytes(2, "little")


class PacketParser(FrameParser[Packet | Corrupt]):
    """Incremental parser: `feed(data)` returns the packets (and corrupt frames) completed."""

    HEADER = HEADER
    HEAD_SIZE = 7  # FF FF FD 00, id, length (2 bytes)

    def _frame_size(self, head: bytes) -> int | None:
        length = int.from_bytes(head[5:7], "little")
        if head[4] > 0xFE or length < 3 or length > MAX_LENGTH:
            return None
        return 7 + length

    def _decode(self, frame: bytes) -> Packet | Corrupt:
        servo_id = frame[4]
        if crc16(frame[:-2]) != int.from_bytes(frame[-2:], "little"):
            return Corrupt(servo_id, frame)
        body = unstuff(frame[7:-2])
        if body[0] == STATUS and len(body) >= 2:
            return Packet(servo_id, STATUS, body[2:], body[1])
        return Packet(servo_id, body[0], body[1:])
