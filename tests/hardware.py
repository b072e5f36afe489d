"""Helpers for tests of the servo-bus drivers: a simulated bus on a pty and polling waits."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any
from unittest import mock

from arena.drivers import servo_arm
from arena.drivers.usb_slave import UsbSlave
from arena.feetech import registers as reg
from arena.feetech.bus import FeetechBus
from arena.feetech.sim import SimBus
from arena.protocol.errors import ErrorCode
from arena.protocol.rest import UsbSlaveBody
from arena.robot.events import FaultReported
from arena.robot.handle import Robot
from arena.robot.model import RobotModel
from arena.server.drivers import usb_slave_config
from arena.servo.health import HealthLimits
from arena.servo.interface import ServoBus, ServoFamily
from arena.servo.ports import DEFAULT_TIMEOUT_MARGIN
from arena.servo.sim_pty import PtySimBus
from arena.servo.worker import WorkerSettings
from tests.conftest import eventually

# The reply timeout's wall-clock part. A starved simulator cannot trip it: the buses of a
# running simulator wait for it too (`PtySimBus.servo_bus`); only servos silent on purpose time out.
TEST_TIMEOUT_MARGIN = 0.05
_SIMS: dict[str, PtySimBus] = {}  # the running simulators by port


def open_test_bus(port: str) -> ServoBus:
    """A bus with the test timeout margin, paced by the simulator on `port` if one runs (of
    the simulator's family; Feetech's otherwise)."""
    sim = _SIMS.get(port)
    if sim is None:
        return FeetechBus(port, timeout_margin=TEST_TIMEOUT_MARGIN)
    return sim.servo_bus(TEST_TIMEOUT_MARGIN)


def _server_bus(family: ServoFamily, port: str, baud: int) -> ServoBus:
    # What a server's arm opens (`ServoArm`'s default): the production margin, but paced by
    # the simulator on that port, so a loaded machine does not make its servos look silent.
    sim = _SIMS.get(port)
    if sim is None:
        return family.open_bus(port, baud)
    return sim.servo_bus(DEFAULT_TIMEOUT_MARGIN)


def usb_slave(
    sim: PtySimBus,
    model: RobotModel,
    calibration: Path | None = None,
    *,
    lost_after: int = 5,
    **config: object,
) -> UsbSlave:
    """A real `UsbSlave` on the simulated bus (control loop at 200 Hz)."""
    body = UsbSlaveBody(port=str(sim.link), **config)  # type: ignore[arg-type]
    settings = WorkerSettings(
        rate=200.0, reconnect_interval=0.1, limits=HealthLimits(lost_after=lost_after)
    )
    return UsbSlave(
        usb_slave_config(body), model, calibration, settings=settings, open_bus=open_test_bus
    )


async def wait_joined(robot: Robot) -> None:
    """Wait until every slave of `robot` follows its targets (an arm joins on its first
    report: a command sent before may find the robot taking the arm's pose)."""
    await eventually(
        lambda: not any(slave.joining for slave in robot.snapshot().slaves), what="the join"
    )


async def fault_of(events: Any, code: ErrorCode, what: str) -> FaultReported:
    """The first fault with `code` among a robot subscription's `events`, waited for."""
    found: list[FaultReported] = []

    def seen() -> bool:
        found.extend(e for e in events.drain() if isinstance(e, FaultReported))
        return any(f.code == code for f in found)

    await eventually(seen, what=what)
    return next(f for f in found if f.code == code)


def servo_goals(sim: PtySimBus) -> dict[int, int]:
    """Goal_Position of every simulated servo."""
    with sim.paused() as bus:
        return {sid: servo.peek(reg.GOAL_POSITION) for sid, servo in bus.servos.items()}


def servo_torque(sim: PtySimBus) -> dict[int, int]:
    """Torque_Enable of every simulated servo."""
    with sim.paused() as bus:
        return {sid: servo.peek(reg.TORQUE_ENABLE) for sid, servo in bus.servos.items()}


def running_sim(tmp_path: Path, **kwargs: object) -> Iterator[PtySimBus]:
    """A started `PtySimBus` at `tmp_path/ttySIM0` (a fixture body). While it runs, the buses
    opened on its port, by tests or by a server's arms, wait for it (see `open_test_bus`)."""
    bus = kwargs.pop("bus", None) or SimBus()
    sim = PtySimBus(tmp_path / "ttySIM0", bus, **kwargs)  # type: ignore[arg-type]
    sim.start()
    _SIMS[str(sim.link)] = sim
    try:
        with mock.patch.object(servo_arm, "open_family_bus", _server_bus):
            yield sim
    finally:
        del _SIMS[str(sim.link)]
        sim.close()
