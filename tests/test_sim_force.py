"""The simulated buses' load model: a stop a test places, load rising on it up to the torque the
registers allow, temperature following the load in the bus's own time (passed in: exact)."""

from __future__ import annotations

import math

import pytest

from arena.feetech import registers as fr
from arena.feetech.packets import Instruction as FI
from arena.feetech.packets import Packet as FPacket
from arena.feetech.sim import OVERLOAD_AFTER_S
from arena.feetech.sim import SimBus as FeetechSim
from arena.servo.sim_pty import AMBIENT_C, COOLING_PER_S, HEATING_C_PER_S


def f_write(bus: FeetechSim, sid: int, register: fr.Register, value: int, now: float) -> None:
    params = bytes([register.address]) + register.encode(value)
    bus.handle(FPacket(sid, FI.WRITE, params), now)


def f_read(bus: FeetechSim, sid: int, register: fr.Register, now: float) -> int:
    (reply,) = bus.handle(FPacket(sid, FI.READ, bytes([register.address, register.size])), now)
    return register.decode(reply.data[5:-1])


def test_a_feetech_servo_stops_at_the_obstacle_and_pushes_at_its_torque_limit() -> None:
    bus = FeetechSim()
    bus.servo(6).place_obstacle(2300)
    f_write(bus, 6, fr.TORQUE_ENABLE, 1, 0.0)
    f_write(bus, 6, fr.GOAL_POSITION, 2800, 0.0)
    assert f_read(bus, 6, fr.PRESENT_POSITION, 0.05) < 2300  # on its way, moving freely
    assert f_read(bus, 6, fr.PRESENT_LOAD, 0.05) < 200
    assert f_read(bus, 6, fr.PRESENT_POSITION, 0.5) == 2300  # held by the stop
    assert f_read(bus, 6, fr.PRESENT_LOAD, 0.5) == 1000  # pushing with all it has
    # Half the torque limit: half the load, and no overload trip however long it pushes.
    f_write(bus, 6, fr.TORQUE_LIMIT, 500, 0.5)
    assert f_read(bus, 6, fr.PRESENT_LOAD, 0.6) == 500
    (status,) = bus.handle(FPacket(6, FI.PING, b""), 0.6 + 3 * OVERLOAD_AFTER_S)
    assert status.data[4] == 0 and f_read(bus, 6, fr.TORQUE_ENABLE, 10.0) == 1
    # A goal just past the stop pushes less (the position loop's error is small).
    f_write(bus, 6, fr.GOAL_POSITION, 2310, 10.0)
    assert 0 < f_read(bus, 6, fr.PRESENT_LOAD, 10.1) < 500
    # Back from the stop: it moves away freely, and the load is gone.
    f_write(bus, 6, fr.GOAL_POSITION, 2000, 10.1)
    assert f_read(bus, 6, fr.PRESENT_POSITION, 11.0) == 2000
    assert f_read(bus, 6, fr.PRESENT_LOAD, 11.1) == 0
    # Full torque on the stop for longer than the protection allows: overload, torque off.
    bus.servo(6).place_obstacle(1900)
    f_write(bus, 6, fr.TORQUE_LIMIT, 1000, 11.0)
    f_write(bus, 6, fr.GOAL_POSITION, 1500, 11.0)
    (status,) = bus.handle(FPacket(6, FI.PING, b""), 11.2 + OVERLOAD_AFTER_S)
    assert status.data[4] & fr.ErrorBit.OVERLOAD
    assert f_read(bus, 6, fr.TORQUE_ENABLE, 11.2 + OVERLOAD_AFTER_S) == 0


def test_a_feetech_servo_heats_with_its_load_and_cools_at_rest() -> None:
    bus = FeetechSim()
    servo = bus.servo(6)
    servo.place_obstacle(2100)
    f_write(bus, 6, fr.TORQUE_LIMIT, 500, 0.0)
    f_write(bus, 6, fr.TORQUE_ENABLE, 1, 0.0)
    f_write(bus, 6, fr.GOAL_POSITION, 2800, 0.0)
    f_read(bus, 6, fr.PRESENT_LOAD, 0.1)  # (on the stop from here)
    # At half load it settles at a quarter of the full-load rise, exactly as the model says.
    settled = AMBIENT_C + HEATING_C_PER_S * 0.25 / COOLING_PER_S
    expected = settled + (servo.temperature - settled) * math.exp(-COOLING_PER_S * 20.0)
    assert f_read(bus, 6, fr.PRESENT_TEMPERATURE, 20.1) == round(expected)
    assert servo.temperature == pytest.approx(expected)
    hot = servo.temperature
    assert hot > AMBIENT_C + 10
    f_write(bus, 6, fr.GOAL_POSITION, 2100, 20.1)  # no push: no load, it cools
    assert f_read(bus, 6, fr.PRESENT_LOAD, 20.2) == 0
    assert f_read(bus, 6, fr.PRESENT_TEMPERATURE, 60.0) < hot - 5
    assert servo.temperature > AMBIENT_C


def test_a_dynamixel_servo_obeys_its_current_limit_and_goal_current() -> None:
    pytest.importorskip("dynamixel_sdk")
    from arena.dynamixel import registers as dr
    from arena.dynamixel.packets import Instruction as DI
    from arena.dynamixel.packets import Packet as DPacket
    from arena.dynamixel.sim import SimBus as DynamixelSim

    bus = DynamixelSim()

    def write(sid: int, register: dr.Register, value: int, now: float) -> None:
        params = register.address.to_bytes(2, "little") + register.encode(value)
        bus.handle(DPacket(sid, DI.WRITE, params), now)

    def read(sid: int, register: dr.Register, now: float) -> int:
        params = register.address.to_bytes(2, "little") + register.size.to_bytes(2, "little")
        (reply,) = bus.handle(DPacket(sid, DI.READ, params), now)
        return register.decode(reply.data[9:-2])

    gripper = bus.servo(6)  # an XL330-M288: Present_Current in mA, full at 1750
    gripper.place_obstacle(2300)
    write(6, dr.TORQUE_ENABLE, 1, 0.0)
    write(6, dr.GOAL_POSITION, 2800, 0.0)
    assert read(6, dr.PRESENT_POSITION, 0.5) == 2300
    assert read(6, dr.PRESENT_CURRENT, 0.5) == 1750
    # Current-based position mode (torque off to change it), Goal_Current a third of the limit.
    write(6, dr.TORQUE_ENABLE, 0, 0.5)
    write(6, dr.OPERATING_MODE, dr.OperatingMode.CURRENT_POSITION, 0.5)
    write(6, dr.TORQUE_ENABLE, 1, 0.5)
    write(6, dr.GOAL_CURRENT, 583, 0.5)
    write(6, dr.GOAL_POSITION, 2800, 0.5)
    assert read(6, dr.PRESENT_CURRENT, 0.6) == 583
    # A lower Current_Limit (EEPROM: torque off to write it) caps the goal current too.
    write(6, dr.TORQUE_ENABLE, 0, 0.6)
    write(6, dr.CURRENT_LIMIT, 300, 0.6)
    write(6, dr.TORQUE_ENABLE, 1, 0.6)
    write(6, dr.GOAL_POSITION, 2800, 0.6)
    assert read(6, dr.PRESENT_CURRENT, 0.7) == 300
    assert read(6, dr.PRESENT_TEMPERATURE, 60.0) > AMBIENT_C + 1  # it heats (less: lower load)
    # An XL430 reads its load in tenths of a percent.
    bus.servo(2).place_obstacle(2100)
    write(2, dr.TORQUE_ENABLE, 1, 60.0)
    write(2, dr.GOAL_POSITION, 2600, 60.0)
    assert read(2, dr.PRESENT_CURRENT, 60.5) == 1000
    assert read(2, dr.HARDWARE_ERROR_STATUS, 60.5 + 2.5) & dr.HardwareError.OVERLOAD
    assert read(2, dr.TORQUE_ENABLE, 63.0) == 0
