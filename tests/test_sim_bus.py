"""The simulated STS3215 bus, driven packet by packet with time passed in."""

from __future__ import annotations

import pytest

from arena.feetech import registers as reg
from arena.feetech.packets import Instruction, Packet, PacketParser, encode
from arena.feetech.sim import MAX_SPEED, OVERLOAD_AFTER_S, SimBus


def ask(
    bus: SimBus, servo_id: int, code: Instruction, params: bytes, now: float = 0.0
) -> list[Packet]:
    """Send one instruction through the codec, as bytes would go over the wire."""
    (packet,) = PacketParser().feed(encode(servo_id, code, params))
    assert isinstance(packet, Packet)
    replies = bus.handle(packet, now)
    parsed = PacketParser().feed(b"".join(r.data for r in replies))
    assert all(isinstance(p, Packet) for p in parsed)
    return parsed  # type: ignore[return-value]


def write(bus: SimBus, servo_id: int, register: reg.Register, value: int, now: float = 0.0) -> None:
    ask(bus, servo_id, Instruction.WRITE, bytes([register.address]) + register.encode(value), now)


def read(bus: SimBus, servo_id: int, register: reg.Register, now: float = 0.0) -> int:
    (reply,) = ask(bus, servo_id, Instruction.READ, bytes([register.address, register.size]), now)
    return register.decode(reply.params)


def test_ping_read_and_the_model_number() -> None:
    bus = SimBus()
    (reply,) = ask(bus, 3, Instruction.PING, b"")
    assert (reply.servo_id, reply.code, reply.params) == (3, 0, b"")
    assert read(bus, 3, reg.MODEL_NUMBER) == reg.STS3215_MODEL
    assert ask(bus, 9, Instruction.PING, b"") == []  # nobody with id 9


def test_eeprom_is_locked_and_read_only_registers_stay() -> None:
    bus = SimBus()
    write(bus, 1, reg.HOMING_OFFSET, 100)
    assert read(bus, 1, reg.HOMING_OFFSET) == 0  # locked: ignored
    write(bus, 1, reg.LOCK, 0)
    write(bus, 1, reg.HOMING_OFFSET, -100)
    assert read(bus, 1, reg.HOMING_OFFSET) == -100
    # Present = actual - homing.
    assert read(bus, 1, reg.PRESENT_POSITION) == 2148
    write(bus, 1, reg.PRESENT_POSITION, 5)
    assert read(bus, 1, reg.PRESENT_POSITION) == 2148


def test_reg_write_waits_for_action_and_broadcast_has_no_reply() -> None:
    bus = SimBus()
    ask(
        bus,
        2,
        Instruction.REG_WRITE,
        bytes([reg.GOAL_POSITION.address]) + reg.GOAL_POSITION.encode(100),
    )
    assert read(bus, 2, reg.GOAL_POSITION) == 2048
    assert ask(bus, reg.BROADCAST_ID, Instruction.ACTION, b"") == []
    assert read(bus, 2, reg.GOAL_POSITION) == 100


def test_sync_write_and_sync_read() -> None:
    bus = SimBus()
    body = b"".join(bytes([sid]) + reg.GOAL_POSITION.encode(1000 + sid) for sid in (1, 2, 3))
    replies = ask(bus, reg.BROADCAST_ID, Instruction.SYNC_WRITE, bytes([42, 2]) + body)
    assert replies == []
    got = ask(bus, reg.BROADCAST_ID, Instruction.SYNC_READ, bytes([42, 2, 3, 1, 2]))
    assert [(p.servo_id, reg.GOAL_POSITION.decode(p.params)) for p in got] == [
        (3, 1003),
        (1, 1001),
        (2, 1002),
    ]


def test_motion_follows_the_goal_at_the_servo_speed_only_with_torque() -> None:
    bus = SimBus()
    write(bus, 1, reg.GOAL_POSITION, 3048, now=0.0)
    assert read(bus, 1, reg.PRESENT_POSITION, now=1.0) == 2048  # torque off: it stays
    write(bus, 1, reg.TORQUE_ENABLE, 1, now=1.0)
    halfway = read(bus, 1, reg.PRESENT_POSITION, now=1.0 + 500 / MAX_SPEED)
    assert halfway == pytest.approx(2548, abs=2)
    assert read(bus, 1, reg.MOVING, now=1.0 + 500 / MAX_SPEED) == 1
    assert read(bus, 1, reg.PRESENT_POSITION, now=2.0) == 3048
    assert read(bus, 1, reg.MOVING, now=2.1) == 0
    # A slower Goal_Velocity is honoured.
    write(bus, 1, reg.GOAL_VELOCITY, 100, now=3.0)
    write(bus, 1, reg.GOAL_POSITION, 3148, now=3.0)
    assert read(bus, 1, reg.PRESENT_POSITION, now=3.5) == pytest.approx(3098, abs=2)


def test_a_stalled_servo_heats_up_and_trips_overload() -> None:
    bus = SimBus()
    bus.servo(4).faults.stalled = True
    write(bus, 4, reg.TORQUE_ENABLE, 1)
    write(bus, 4, reg.GOAL_POSITION, 2500)
    (status,) = ask(bus, 4, Instruction.PING, b"", now=0.5)
    assert status.code == 0
    assert read(bus, 4, reg.PRESENT_LOAD, now=0.5) == 1000
    (status,) = ask(bus, 4, Instruction.PING, b"", now=OVERLOAD_AFTER_S + 0.1)
    assert status.code & reg.ErrorBit.OVERLOAD
    assert read(bus, 4, reg.TORQUE_ENABLE, now=OVERLOAD_AFTER_S + 0.1) == 0  # protection
    assert read(bus, 4, reg.PRESENT_TEMPERATURE) > 30


def test_injected_faults() -> None:
    bus = SimBus()
    bus.servo(1).faults.silent = True
    assert ask(bus, 1, Instruction.PING, b"") == []
    bus.servo(2).faults.corrupt = True
    (packet,) = PacketParser().feed(encode(2, Instruction.PING, b""))
    assert isinstance(packet, Packet)
    raw = b"".join(r.data for r in bus.handle(packet, 0.0))
    assert type(PacketParser().feed(raw)[0]).__name__ == "Corrupt"
    bus.servo(3).faults.late = 0.05
    assert bus.handle(Packet(3, Instruction.PING, b""), 0.0)[0].delay == pytest.approx(0.05)
    bus.servo(5).faults.error_bits = int(reg.ErrorBit.VOLTAGE)
    (status,) = ask(bus, 5, Instruction.PING, b"")
    assert status.code == reg.ErrorBit.VOLTAGE
    bus.servo(6).temperature = 75
    (status,) = ask(bus, 6, Instruction.PING, b"")
    assert status.code & reg.ErrorBit.OVERHEAT
