"""Talking to real STS3215 servos through `scservo_sdk` (feetech-servo-sdk) and pyserial.

A `ServoBus` is used from one thread only: the SDK's port is not thread-safe. It works around
the SDK's traps (see the so-arm100 robot notes):

- stale input: `clearPort()` only flushes output, so a late reply would be taken as the answer
  to the next request. `ArenaPort.clearPort` drops pending input before every transmission.
- busy-waiting: the SDK polls a non-blocking port until its timeout. `ArenaPort.readPort`
  sleeps in `select()` until bytes arrive or the deadline passes.
- timeouts: the SDK waits a fixed 34 ms for any reply; ours is the wire time plus a margin.
- one silent servo fails a whole `GroupSyncRead`: `sync_read` collects replies one by one, so
  every servo that did answer is kept and the silent one is named.
- byte order: `PacketHandler(0)` sets a process-wide global; `open()` sets it again.
"""

from __future__ import annotations

import errno
import os
import select
import stat
import termios
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import scservo_sdk as sdk
import serial
from serial.tools import list_ports

from arena.feetech import registers as reg
from arena.protocol.errors import ArenaError, ErrorCode

# USB ids of the serial adapters seen on SO-100 arms.
ADAPTERS: dict[tuple[int, int], str] = {(0x1A86, 0x7523): "CH340", (0x1A86, 0x55D3): "CH343"}
DEFAULT_TIMEOUT_MARGIN = 0.010  # seconds on top of the wire time before a reply is missing


class BusError(ArenaError):
    """The bus itself failed (port gone, unreadable): the driver closes it and reconnects."""


@dataclass
class SyncReadResult:
    """What a sync read got back: data and error byte per servo that answered, and the rest."""

    data: dict[int, bytes] = field(default_factory=dict)
    errors: dict[int, int] = field(default_factory=dict)
    missing: list[int] = field(default_factory=list)
    corrupt: list[int] = field(default_factory=list)


class ArenaPort(sdk.PortHandler):  # type: ignore[misc]
    """The SDK's port with the traps fixed (see the module docstring). Public for
    `sim_pty`, whose paced port is this one waiting also for the simulator."""

    def __init__(self, port_name: str, timeout_margin: float) -> None:
        super().__init__(port_name)
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


class ServoBus:
    """Servos on one serial port. Not thread-safe: one thread owns it."""

    def __init__(
        self,
        port: str,
        baud: int = 1_000_000,
        *,
        timeout_margin: float = DEFAULT_TIMEOUT_MARGIN,
    ) -> None:
        self.port_name = port
        self.baud = baud
        self._port = ArenaPort(port, timeout_margin)
        self._handler: Any = None

    # -- port -------------------------------------------------------------------------------

    def open(self) -> None:
        """Open the port; problems raise `BusError` with what to do about them."""
        self._handler = sdk.PacketHandler(0)  # STS servos are little-endian (process-global)
        self._port.baudrate = self.baud
        if self._port.getCFlagBaud(self.baud) <= 0:
            raise BusError(ErrorCode.INVALID_CONFIG, f"Baud rate {self.baud} is not supported.")
        try:
            self._port.setupPort(self.baud)
        except (serial.SerialException, OSError, termios.error) as exc:
            raise port_error(self.port_name, exc) from None

    def close(self) -> None:
        """Close the port (no error if it is gone already)."""
        if self._port.is_open:
            try:
                self._port.closePort()
            except (serial.SerialException, OSError, termios.error):
                self._port.is_open = False

    @property
    def is_open(self) -> bool:
        """Whether the port is open."""
        return bool(self._port.is_open)

    # -- transactions -----------------------------------------------------------------------

    def ping(self, servo_id: int) -> int:
        """The servo's model number; `ArenaError(SERVO_TIMEOUT)` if it does not answer."""
        model, result, _ = self._call(self._handler.ping, self._port, servo_id)
        self._check(result, servo_id, "ping")
        return int(model)

    def read(self, servo_id: int, register: reg.Register) -> int:
        """One register of one servo."""
        data, result, _ = self._call(
            self._handler.readTxRx, self._port, servo_id, register.address, register.size
        )
        self._check(result, servo_id, f"read {register.name}")
        return register.decode(bytes(data))

    def write(self, servo_id: int, register: reg.Register, value: int) -> None:
        """Write one register and wait for the servo's answer (broadcast: no answer)."""
        data = list(register.encode(value))
        if servo_id == reg.BROADCAST_ID:
            result = self._call(
                self._handler.writeTxOnly,
                self._port,
                servo_id,
                register.address,
                register.size,
                data,
            )
        else:
            result, _ = self._call(
                self._handler.writeTxRx,
                self._port,
                servo_id,
                register.address,
                register.size,
                data,
            )
        self._check(result, servo_id, f"write {register.name}")

    def sync_write(self, register: reg.Register, values: Mapping[int, int]) -> None:
        """Write the same register of several servos in one packet (no answer)."""
        if not values:
            return
        params: list[int] = []
        for servo_id, value in values.items():
            params.append(servo_id)
            params.extend(register.encode(value))
        result = self._call(
            self._handler.syncWriteTxOnly,
            self._port,
            register.address,
            register.size,
            params,
            len(params),
        )
        self._check(result, reg.BROADCAST_ID, f"sync write {register.name}")

    def sync_read(self, address: int, length: int, servo_ids: Sequence[int]) -> SyncReadResult:
        """Read the same bytes of several servos in one request; see `SyncReadResult`."""
        ids = list(servo_ids)
        result = self._call(self._handler.syncReadTx, self._port, address, length, ids, len(ids))
        self._check(result, reg.BROADCAST_ID, "sync read")
        got = SyncReadResult()
        wanted = set(ids)
        while wanted:
            packet, outcome = self._call(self._handler.rxPacket, self._port)
            if outcome == sdk.COMM_SUCCESS:
                servo_id = packet[2]
                if servo_id in wanted:
                    wanted.discard(servo_id)
                    got.errors[servo_id] = packet[4]
                    got.data[servo_id] = bytes(packet[5 : 5 + length])
                continue
            if outcome == sdk.COMM_RX_CORRUPT and len(packet) >= 6 and packet[2] in wanted:
                wanted.discard(packet[2])  # a whole frame with a bad checksum: go on
                got.corrupt.append(packet[2])
                continue
            break  # timeout: whoever has not answered by now is missing
        got.missing = [sid for sid in ids if sid in wanted]
        self._port.is_using = False
        return got

    def sync_read_register(
        self, register: reg.Register, servo_ids: Sequence[int]
    ) -> tuple[dict[int, int], SyncReadResult]:
        """One register of several servos, decoded; and the raw result."""
        got = self.sync_read(register.address, register.size, servo_ids)
        return {sid: register.decode(data) for sid, data in got.data.items()}, got

    def _call(self, method: Any, *args: Any) -> Any:
        try:
            return method(*args)
        except (serial.SerialException, OSError, TypeError, termios.error) as exc:
            # TypeError: the SDK touches `ser` after it was closed under it.
            self._port.is_using = False
            raise BusError(
                ErrorCode.PORT_DISCONNECTED,
                f"The servo bus on {self.port_name} stopped working ({exc}); "
                "check the USB cable and the servo power supply.",
            ) from None

    def _check(self, result: int, servo_id: int, what: str) -> None:
        if result == sdk.COMM_SUCCESS:
            return
        if result == sdk.COMM_RX_TIMEOUT:
            raise ArenaError(ErrorCode.SERVO_TIMEOUT, f"Servo {servo_id} did not answer ({what}).")
        if result == sdk.COMM_RX_CORRUPT:
            raise ArenaError(
                ErrorCode.SERVO_CORRUPT, f"Servo {servo_id} sent a garbled answer ({what})."
            )
        raise BusError(
            ErrorCode.PORT_DISCONNECTED,
            f"{what} on {self.port_name} failed: {self._handler.getTxRxResult(result)}",
        )


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


def find_adapter(ports: Iterable[PortInfo] | None = None) -> str:
    """The one servo adapter's port (CH340/CH343 by USB id); a clear error for none or several."""
    seen = list(system_ports() if ports is None else ports)
    found = [p for p in seen if (p.vid, p.pid) in ADAPTERS]
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
    kinds = " or ".join(f"{name} {v:04x}:{p:04x}" for (v, p), name in ADAPTERS.items())
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
