"""`FeetechBus` (the real scservo_sdk underneath) against the simulated bus: the SDK's traps."""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import scservo_sdk as sdk

from arena.feetech import registers as reg
from arena.feetech.bus import FEETECH, FeetechBus
from arena.protocol.errors import ArenaError, ErrorCode
from arena.servo.sim_pty import PtySimBus
from tests.hardware import open_test_bus, running_sim


@pytest.fixture
def sim(tmp_path: Path) -> Iterator[PtySimBus]:
    yield from running_sim(tmp_path)


@pytest.fixture
def bus(sim: PtySimBus) -> Iterator[FeetechBus]:
    opened = open_test_bus(str(sim.link))
    opened.open()
    yield opened
    opened.close()


def wait_for_bytes(port: Any) -> None:
    """Until the late reply has arrived in the serial port's input buffer (event, not time)."""
    deadline = time.monotonic() + 30
    while not port.in_waiting:
        assert time.monotonic() < deadline, "the late reply never came"
        time.sleep(0.005)


def test_a_late_reply_is_not_taken_as_the_next_answer(sim: PtySimBus, bus: FeetechBus) -> None:
    with sim.paused() as simulated:
        simulated.servo(2).move_by_hand(2148)
        simulated.servo(2).faults.late = 0.12
    with pytest.raises(ArenaError) as missed:
        bus.read(2, reg.PRESENT_POSITION)
    assert missed.value.code is ErrorCode.SERVO_TIMEOUT
    wait_for_bytes(bus._port.ser)  # the late answer (2148) is now waiting in the input buffer
    with sim.paused() as simulated:
        simulated.servo(2).faults.late = 0.0
    assert bus.read(2, reg.HOMING_OFFSET) == 0  # not 2148


def test_the_stock_sdk_port_does_fall_into_that_trap(sim: PtySimBus) -> None:
    # The same exchange through the SDK's own PortHandler: the stale reply answers the read.
    port = sdk.PortHandler(str(sim.link))
    port.openPort()
    handler = sdk.PacketHandler(0)
    try:
        with sim.paused() as simulated:
            simulated.servo(2).move_by_hand(2148)
            simulated.servo(2).faults.late = 0.12
        _, result, _ = handler.read2ByteTxRx(port, 2, reg.PRESENT_POSITION.address)
        assert result == sdk.COMM_RX_TIMEOUT
        wait_for_bytes(port.ser)
        with sim.paused() as simulated:
            simulated.servo(2).faults.late = 0.0
        value, result, _ = handler.read2ByteTxRx(port, 2, reg.HOMING_OFFSET.address)
        assert (result, value) == (sdk.COMM_SUCCESS, 2148)
    finally:
        port.closePort()


def test_one_silent_servo_does_not_hide_the_others(sim: PtySimBus, bus: FeetechBus) -> None:
    with sim.paused() as simulated:
        simulated.servo(3).faults.silent = True
        simulated.servo(5).faults.corrupt = True
    result = bus.sync_read(reg.PRESENT_POSITION.address, 2, [1, 2, 3, 4, 5, 6])
    assert sorted(result.data) == [1, 2, 4, 6]
    assert result.missing == [3]
    assert result.corrupt == [5]


def test_reads_wait_without_burning_a_core(sim: PtySimBus, bus: FeetechBus) -> None:
    with sim.paused() as simulated:
        simulated.servo(1).faults.silent = True
    started_cpu, started = time.thread_time(), time.perf_counter()
    for _ in range(5):
        with pytest.raises(ArenaError):
            bus.read(1, reg.PRESENT_POSITION)
    waited = time.perf_counter() - started
    cpu = time.thread_time() - started_cpu
    assert waited >= 5 * 0.05  # it did wait out each timeout...
    assert cpu < waited / 2  # ...asleep, not polling (the stock SDK spends all of it on CPU)


def test_writes_and_the_eeprom_lock(sim: PtySimBus, bus: FeetechBus) -> None:
    bus.write(1, reg.LOCK, 0)
    bus.write(1, reg.HOMING_OFFSET, -300)
    bus.write(1, reg.LOCK, 1)
    assert bus.read(1, reg.HOMING_OFFSET) == -300
    assert bus.ping(1) == reg.STS3215_MODEL
    bus.write(reg.BROADCAST_ID, reg.TORQUE_ENABLE, 1)
    bus.ping(6)  # no answer to a broadcast: a ping after it says the bus has handled it
    with sim.paused() as simulated:
        assert all(s.peek(reg.TORQUE_ENABLE) == 1 for s in simulated.servos.values())


@pytest.mark.parametrize("family_name", ["feetech", "dynamixel"])
def test_an_arms_own_bus_is_its_familys_on_its_port_at_its_rate(family_name: str) -> None:
    # What a `usb-slave` opens when nothing replaces its bus (a real arm), not yet opened.
    from arena.drivers.servo_arm import open_family_bus
    from arena.dynamixel.bus import DYNAMIXEL, DynamixelBus

    family, kind = (FEETECH, FeetechBus) if family_name == "feetech" else (DYNAMIXEL, DynamixelBus)
    bus = open_family_bus(family, "/dev/ttyACM7", 57_600)
    assert type(bus) is kind
    assert (bus.port_name, bus.baud) == ("/dev/ttyACM7", 57_600)
