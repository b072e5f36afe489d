"""Serial ports for every servo family: the SDK port handler's traps fixed, opening errors that
say what to do, and finding the adapter by its USB id.

Both servo SDKs (Feetech's `scservo_sdk`, ROBOTIS's `dynamixel_sdk`) share one port handler
design, and its traps (see specs/servo-bus.md): `PortFixes` goes before either SDK's
`PortHandler` in a subclass and fixes them.
"""

from __future__ import annotations

import errno
import os
import select
import stat
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

import serial
from serial.tools import list_ports

from arena.protocol.errors import ArenaError, ErrorCode
from arena.servo.interface import BusError

DEFAULT_TIMEOUT_MARGIN = 0.010  # seconds on top of the wire time before a reply is missing


class PortFixes:
    """Mixed in before an SDK's `PortHandler`: exclusive open, stale input dropped before every
    transmission, a reply timeout of wire time plus `margin_ms`, reads that sleep in `select()`
    instead of spinning."""

    ser: Any
    port_name: str
    baudrate: int
    is_open: bool
    tx_time_per_byte: float
    packet_start_time: float
    packet_timeout: float

    def __init__(self, port_name: str, timeout_margin: float) -> None:
        super().__init__(port_name)  # type: ignore[call-arg]
        self.margin_ms = timeout_margin * 1000.0

    def setupPort(self, cflag_baud: int) -> bool:
        # exclusive: a second program on the same adapter would corrupt both conversations.
        self.ser = serial.Serial(
            port=self.port_name, baudrate=self.baudrate, timeout=0, exclusive=True
        )
        self.is_open = True
        self.ser.reset_input_buffer()
        self.tx_time_per_byte = (1000.0 / self.baudrate) * 10.0
        return True

    def clearPort(self) -> None:
        self.ser.reset_input_buffer()

    def setPacketTimeout(self, packet_length: int) -> None:
        self.packet_start_time = self.getCurrentTime()
        self.packet_timeout = self.tx_time_per_byte * packet_length + self.margin_ms

    def readPort(self, length: int) -> bytes:
        data: bytes = self.ser.read(length)
        if data:
            return data
        remaining_ms = self.packet_timeout - self.getTimeSinceStart()
        if remaining_ms > 0:
            select.select([self.ser.fileno()], [], [], remaining_ms / 1000.0)
            data = self.ser.read(length)
        return data

    def getCurrentTime(self) -> float:  # (the SDK's own; declared for the type checker)
        return float(super().getCurrentTime())  # type: ignore[misc]

    def getTimeSinceStart(self) -> float:
        return float(super().getTimeSinceStart())  # type: ignore[misc]


def port_error(port: str, exc: BaseException) -> BusError:
    """A `BusError` saying what went wrong opening `port` and what to do about it."""
    code = getattr(exc, "errno", None)
    text = str(exc)
    if code == errno.ENOENT or "No such file" in text:
        return BusError(
            ErrorCode.PORT_NOT_FOUND,
            f"Serial port {port} does not exist: check that the servo adapter is plugged in "
            "(ls /dev/ttyUSB* /dev/ttyACM*) or leave the port out to find it by USB id.",
        )
    if code in (errno.EACCES, errno.EPERM) or "Permission denied" in text:
        return BusError(
            ErrorCode.PORT_PERMISSION_DENIED,
            f"No permission to open {port}: add your user to the dialout group "
            "(sudo usermod -aG dialout $USER, then log in again) or run with access to it.",
        )
    if code == errno.EBUSY or "exclusively lock" in text or "busy" in text.lower():
        return BusError(
            ErrorCode.PORT_BUSY,
            f"Serial port {port} is in use by another program (another Arena server, LeRobot, "
            "a serial monitor): close it first.",
        )
    return BusError(ErrorCode.PORT_DISCONNECTED, f"Cannot open serial port {port}: {text}")


def check_serial_device(port: str) -> None:
    """Only serial devices: a REST client must not make the server open arbitrary files."""
    try:
        mode = os.stat(port).st_mode
    except OSError as exc:
        raise port_error(port, exc) from None
    if not stat.S_ISCHR(mode):
        raise ArenaError(ErrorCode.INVALID_CONFIG, f"{port} is not a serial device.")


@dataclass(frozen=True, slots=True)
class PortInfo:
    """A serial port as the system lists it."""

    device: str
    vid: int | None = None
    pid: int | None = None
    description: str = ""


def system_ports() -> list[PortInfo]:
    """The serial ports on this machine."""
    return [PortInfo(p.device, p.vid, p.pid, p.description or "") for p in list_ports.comports()]


def find_adapter(
    adapters: Mapping[tuple[int, int], str], ports: Iterable[PortInfo] | None = None
) -> str:
    """The one servo adapter's port (one of `adapters`, by USB id); a clear error for none or
    several."""
    seen = list(system_ports() if ports is None else ports)
    found = [p for p in seen if (p.vid, p.pid) in adapters]
    if len(found) == 1:
        return found[0].device
    listing = (
        ", ".join(
            f"{p.device} ({p.vid:04x}:{p.pid:04x})"
            if p.vid is not None and p.pid is not None
            else p.device
            for p in seen
        )
        or "none"
    )
    kinds = " or ".join(f"{name} {v:04x}:{p:04x}" for (v, p), name in adapters.items())
    if not found:
        raise ArenaError(
            ErrorCode.PORT_NOT_FOUND,
            f"No servo adapter ({kinds}) is plugged in; serial ports seen: {listing}. "
            "Plug it in or give the port.",
        )
    raise ArenaError(
        ErrorCode.PORT_NOT_FOUND,
        f"Several servo adapters found ({', '.join(p.device for p in found)}); "
        "say which one with the port setting.",
    )
