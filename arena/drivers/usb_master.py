"""The USB master: a leader arm, moved by hand, commands the robot.

Torque stays off on the leader. Its present positions are read on its own bus thread (the same
`BusWorker` as the USB slave), turned into degrees through the leader's calibration, and sent
as commands whenever a joint moved more than the dead band, at most as often as the robot's
rate limit allows (the newest pose wins). It claims the robot like any master (no takeover), an
e-stop ends it for good, and losing the leader's bus is a lost master (the loss policy applies).
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Callable, Mapping
from pathlib import Path

import trio

from arena.drivers.bus_bridge import BusBridge
from arena.drivers.config import UsbMasterConfig
from arena.drivers.refusals import Refusals
from arena.drivers.servo_arm import ServoArm
from arena.protocol.errors import ErrorCode
from arena.robot.links import MasterLink
from arena.robot.model import RobotModel
from arena.robot.motion import Command, JointGoal
from arena.servo.health import ServoFault
from arena.servo.interface import ServoBus
from arena.servo.worker import Lost, Reading, WorkerSettings

log = logging.getLogger(__name__)

#: Refusals after which the leader stops for good.
_FINAL_REFUSALS = frozenset({ErrorCode.ESTOPPED, ErrorCode.NOT_OWNER})


class UsbMaster(ServoArm):
    """See the module docstring. `open_bus` replaces the serial bus (tests, benchmarks)."""

    kind = "usb-master"
    autonomous = True  # an e-stop ends it: a leader arm must not drive on after a reset
    takes_over = False

    def __init__(
        self,
        config: UsbMasterConfig,
        model: RobotModel,
        calibration_file: Path | None = None,
        *,
        settings: WorkerSettings | None = None,
        open_bus: Callable[[str], ServoBus] | None = None,
    ) -> None:
        super().__init__(
            config.port,
            config.baud_rate,
            model,
            calibration_file,
            # Torque off, always: the leader is moved by hand.
            dataclasses.replace(
                settings or WorkerSettings(rate=config.rate), torque_on_connect=False
            ),
            open_bus,
            leader=True,
        )
        self.config = config
        self.sent = 0
        self.refusals = Refusals()

    @property
    def description(self) -> str:
        """What it is, in words (told to a master it takes over from)."""
        return f"leader arm on {self.config.port or 'the USB adapter'}"

    async def run(self, link: MasterLink) -> None:
        """Mirror the leader onto the robot until detached, e-stopped or the bus is lost."""
        await self.prepare()
        assert self.worker is not None and self.bridge is not None
        if not self.calibrated:
            log.warning("usb-master on %s: uncalibrated, raw 2048 is 0 deg", self.port)
        try:
            await self._mirror(link, self.bridge)
        finally:
            await self.close()

    async def _mirror(self, link: MasterLink, bridge: BusBridge) -> None:
        interval = 1.0 / min(self.config.rate, self.model.safety.command_rate)
        last_sent: dict[str, float] | None = None
        last_at = -math.inf
        while True:
            reading, events = await bridge.next()
            for event in events:
                if isinstance(event, Lost):
                    await link.lost(f"leader arm bus on {self.port}: {event.reason}")
                    return
                if isinstance(event, ServoFault):
                    await self.tell_fault(link, event)
            if reading is None:
                continue
            if link.paused:  # sends nothing until resumed, then the pose it finds then
                await link.wait_resumed()
                last_sent = None
                continue
            pose = self._pose(reading)
            if last_sent is not None and not _moved(pose, last_sent, self.config.deadband):
                continue
            wait = last_at + interval - trio.current_time()
            if wait > 0:  # the robot's rate limit: wait, then send the newest pose there is
                await trio.sleep(wait)
                newer = bridge.take_reading()
                if newer is not None:
                    pose = self._pose(newer)
            last_at = trio.current_time()
            result = await link.command(
                Command(tuple(JointGoal(n, v) for n, v in pose.items()), source="leader-arm")
            )
            self.sent += 1
            if result.accepted:
                last_sent = pose
                continue
            self.refusals.append((result.code, result.message))
            if result.code in _FINAL_REFUSALS:
                return  # stopped for good: a leader never resumes by itself

    def _pose(self, reading: Reading) -> dict[str, float]:
        return self.calibration.to_values(reading.positions, self.spans)


def _moved(pose: Mapping[str, float], last: Mapping[str, float], deadband: float) -> bool:
    """Whether any joint moved more than `deadband` degrees since the last command."""
    return any(abs(value - last.get(name, math.inf)) > deadband for name, value in pose.items())
