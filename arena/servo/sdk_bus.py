"""What a servo bus does the same way whichever SDK (Feetech's `scservo_sdk`, ROBOTIS's
`dynamixel_sdk`) carries its packets: both SDKs share one port and packet-handler design, so
opening the port, one-servo transactions, sync writes, collecting a sync read's replies one by
one, and turning the SDK's result numbers into Arena's errors are written once here.

A family's bus (`arena.feetech.bus.FeetechBus`, `arena.dynamixel.bus.DynamixelBus`) subclasses
`SdkBus` and says where its status packets keep the servo id, the error byte and the data, and
everything that differs: its registers, its writes, its operating modes, its fault flags.
"""

from __future__ import annotations

import termios
from collections.abc import Mapping, Sequence
from typing import Any, ClassVar, Protocol

import serial

from arena.protocol.errors import ArenaError, ErrorCode
from arena.servo.interface import BusError, SyncReadResult, Telemetry
from arena.servo.ports import DEFAULT_TIMEOUT_MARGIN, port_error

#: What the SDKs raise when the port fails under them (TypeError: the SDK touches `ser` after it
#: was closed under it).
PORT_FAILURES = (serial.SerialException, OSError, TypeError, termios.error)


class SdkRegister(Protocol):
    """A register of either family: where it is, how wide, how its value is coded."""

    @property
    def name(self) -> str: ...

    @property
    def address(self) -> int: ...

    @property
    def size(self) -> int: ...

    def encode(self, value: int) -> bytes: ...

    def decode(self, data: bytes) -> int: ...


class SdkBus:
    """Servos on one serial port through an SDK. Not thread-safe: one thread owns it.

    A subclass sets `sdk` (the SDK module), `port_class` (its port, `PortFixes` mixed in),
    the status packet's layout (`ID_AT`, `DATA_AT`, `MIN_FRAME`), its registers, and
    `_new_handler`.
    """

    sdk: ClassVar[Any]
    port_class: ClassVar[type[Any]]
    ID_AT: ClassVar[int]  # index of the servo id in a status packet
    DATA_AT: ClassVar[int]  # index of its first data byte
    MIN_FRAME: ClassVar[int]  # the shortest whole status packet (a corrupt one counts then)
    BROADCAST_ID: ClassVar[int] = 0xFE
    #: The family's registers for what both families do alike (below).
    PRESENT_POSITION: ClassVar[SdkRegister]
    GOAL_POSITION: ClassVar[SdkRegister]
    TORQUE_ENABLE: ClassVar[SdkRegister]
    HOMING_OFFSET: ClassVar[SdkRegister]

    def __init__(
        self,
        port: str,
        baud: int = 1_000_000,
        *,
        timeout_margin: float = DEFAULT_TIMEOUT_MARGIN,
        port_handler: Any = None,
    ) -> None:
        self.port_name = port
        self.baud = baud
        self._port: Any = port_handler or self.port_class(port, timeout_margin)
        self._handler: Any = None

    def _new_handler(self) -> Any:
        """The SDK's packet handler (called at every `open`)."""
        raise NotImplementedError

    def _reply_error(self, packet: Sequence[int]) -> int:
        """The fault flags (`FaultBit`) a status packet carries (0: the family reads them
        elsewhere)."""
        return 0

    def _rx_args(self) -> tuple[Any, ...]:
        """Extra arguments of the SDK's `syncReadTx` and `rxPacket`."""
        return ()

    # -- port -------------------------------------------------------------------------------

    def open(self) -> None:
        """Open the port; problems raise `BusError` with what to do about them."""
        self._handler = self._new_handler()
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

    def read(self, servo_id: int, register: SdkRegister) -> int:
        """One register of one servo."""
        data, result, _ = self._call(
            self._handler.readTxRx, self._port, servo_id, register.address, register.size
        )
        self._check(result, servo_id, f"read {register.name}")
        return register.decode(bytes(data))

    def sync_write(self, register: SdkRegister, values: Mapping[int, int]) -> None:
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
        self._check(result, self.BROADCAST_ID, f"sync write {register.name}")

    def sync_read(self, address: int, length: int, servo_ids: Sequence[int]) -> SyncReadResult:
        """Read the same bytes of several servos in one request, their replies collected one by
        one: one silent servo does not fail the others (the SDK's group read would), and is
        named in `missing`."""
        ids = list(servo_ids)
        extra = self._rx_args()
        result = self._call(
            self._handler.syncReadTx, self._port, address, length, ids, len(ids), *extra
        )
        self._check(result, self.BROADCAST_ID, "sync read")
        got = SyncReadResult()
        wanted = set(ids)
        while wanted:
            packet, outcome = self._call(self._handler.rxPacket, self._port, *extra)
            if outcome == self.sdk.COMM_SUCCESS:
                servo_id = packet[self.ID_AT]
                # A reply of another size answers an earlier request that timed out (its bytes
                # came after the port was cleared for this one): a telemetry block read as a
                # position would be step 0, half a turn away. It is not this servo's answer.
                if servo_id in wanted and len(packet) - self.MIN_FRAME == length:
                    wanted.discard(servo_id)
                    got.errors[servo_id] = self._reply_error(packet)
                    got.data[servo_id] = bytes(packet[self.DATA_AT : self.DATA_AT + length])
                continue
            if (
                outcome == self.sdk.COMM_RX_CORRUPT
                and len(packet) >= self.MIN_FRAME
                and packet[self.ID_AT] in wanted
            ):
                wanted.discard(packet[self.ID_AT])  # a whole frame with a bad checksum: go on
                got.corrupt.append(packet[self.ID_AT])
                continue
            break  # timeout: whoever has not answered by now is missing
        got.missing = [sid for sid in ids if sid in wanted]
        self._port.is_using = False
        return got

    def sync_read_register(
        self, register: SdkRegister, servo_ids: Sequence[int]
    ) -> tuple[dict[int, int], SyncReadResult]:
        """One register of several servos, decoded; and the raw result."""
        got = self.sync_read(register.address, register.size, servo_ids)
        return {sid: register.decode(data) for sid, data in got.data.items()}, got

    # -- the parts of `arena.servo.interface.ServoBus` both families do alike ---------------

    def read_positions(self, servo_ids: Sequence[int]) -> tuple[dict[int, int], SyncReadResult]:
        """Present positions of several servos in one request; and what came back."""
        return self.sync_read_register(self.PRESENT_POSITION, servo_ids)

    def write_goals(self, goals: Mapping[int, int]) -> None:
        """Goal_Position of several servos in one packet."""
        self.sync_write(self.GOAL_POSITION, goals)

    def set_torque(self, servo_ids: Sequence[int], *, on: bool) -> None:
        """Torque_Enable of every servo named."""
        self.sync_write(self.TORQUE_ENABLE, dict.fromkeys(servo_ids, 1 if on else 0))

    def read_homings(self, servo_ids: Sequence[int]) -> dict[int, int]:
        """Each servo's Homing_Offset register."""
        return {sid: self.read(sid, self.HOMING_OFFSET) for sid in servo_ids}

    def _call(self, method: Any, *args: Any) -> Any:
        try:
            return method(*args)
        except PORT_FAILURES as exc:
            self._port.is_using = False
            raise BusError(
                ErrorCode.PORT_DISCONNECTED,
                f"The servo bus on {self.port_name} stopped working ({exc}); "
                "check the USB cable and the servo power supply.",
            ) from None

    def _check(self, result: int, servo_id: int, what: str) -> None:
        if result == self.sdk.COMM_SUCCESS:
            return
        if result == self.sdk.COMM_RX_TIMEOUT:
            raise ArenaError(ErrorCode.SERVO_TIMEOUT, f"Servo {servo_id} did not answer ({what}).")
        if result == self.sdk.COMM_RX_CORRUPT:
            raise ArenaError(
                ErrorCode.SERVO_CORRUPT, f"Servo {servo_id} sent a garbled answer ({what})."
            )
        raise BusError(
            ErrorCode.PORT_DISCONNECTED,
            f"{what} on {self.port_name} failed: {self._handler.getTxRxResult(result)}",
        )


def decode_telemetry(
    result: SyncReadResult,
    start: int,
    size: int,
    *,
    position: SdkRegister,
    temperature: SdkRegister,
    load: SdkRegister,
    voltage: SdkRegister,
    full_load: Mapping[int, int] | int,
) -> Telemetry:
    """A sync read of the block of `size` bytes from address `start`, decoded: each field from
    its register (loads as magnitudes, voltages from tenths of a volt); servos whose reply was
    short are left out. `full_load`: the load register's value at full torque (by servo, or
    one for all), for `Telemetry.load_percent`."""

    def field_of(register: SdkRegister, data: bytes) -> int:
        at = register.address - start
        return register.decode(data[at : at + register.size])

    data = {sid: d for sid, d in result.data.items() if len(d) >= size}
    loads = {sid: abs(field_of(load, d)) for sid, d in data.items()}

    def full(servo_id: int) -> int:
        value = full_load if isinstance(full_load, int) else full_load.get(servo_id, 0)
        return max(1, value)

    return Telemetry(
        positions={sid: field_of(position, d) for sid, d in data.items()},
        temperatures={sid: field_of(temperature, d) for sid, d in data.items()},
        loads=loads,
        voltages={sid: field_of(voltage, d) / 10 for sid, d in data.items()},
        load_percent={sid: 100.0 * value / full(sid) for sid, value in loads.items()},
    )
