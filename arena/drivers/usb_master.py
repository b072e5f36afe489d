"""The USB master: a leader arm, moved by hand, commands the robot.

Torque stays off on the leader, but for an `actuated` one's first moments: it is driven to
the follower's pose at the robot's joining speed, then goes limp, so that the hand takes it
where the follower is (no jerk when it starts to command). Its present positions are read on
its own bus thread (the same `BusWorker` as the USB slave), turned into degrees through the
leader's calibration, and sent as commands whenever a joint moved more than the dead band or
is plainly moving (`TREND_CHANGES` changes of its reading in a row the same way: a move is
sent from its start, not once it has left the band), at most as often as the robot's rate
limit allows (the newest pose wins); a pose the leader holds after a move inside the band is
sent once (`SETTLE_AFTER`), so the follower settles where the leader did. It claims the robot
like any master (no takeover), an e-stop ends it for good, and losing the leader's bus is a
lost master (the loss policy applies).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from collections.abc import Callable, Mapping
from pathlib import Path

import trio

from arena.drivers.bus_bridge import BusBridge, wait_future
from arena.drivers.config import UsbMasterConfig
from arena.drivers.refusals import Refusals
from arena.drivers.servo_arm import ServoArm
from arena.protocol.errors import ErrorCode
from arena.robot.links import MasterLink
from arena.robot.model import RobotModel
from arena.robot.motion import Command, JointGoal
from arena.servo.health import ServoFault
from arena.servo.interface import ServoBus
from arena.servo.worker import BusWorker, Lost, Reading, WorkerSettings

log = logging.getLogger(__name__)

#: Refusals after which the leader stops for good.
_FINAL_REFUSALS = frozenset({ErrorCode.ESTOPPED, ErrorCode.NOT_OWNER})
#: Seconds a leader's pose must hold for its last move inside the dead band to be sent.
SETTLE_AFTER = 0.1
#: Changes of a joint's raw reading in a row the same way (readings that hold between them
#: count for nothing) that make a move, sent at once though inside the dead band. A resting
#: leader's encoder flickers (an STS3215's or XL330's reading toggling by a step, now and
#: then two, back and forth): that never makes three changes the same way, while a hand's
#: move does from its start (a slow minimum-jerk move: its third step some 15 ms after its
#: first, its sixth, where it leaves a 0.5 degree band, some 27 ms). Each further step of the
#: run goes out too, at most at the robot's rate limit; LeRobot sends every frame.
TREND_CHANGES = 3


class UsbMaster(ServoArm):
    """See the module docstring. `open_bus` replaces the serial bus (tests, benchmarks)."""

    kind = "usb-master"
    autonomous = True  # an e-stop ends it: a leader arm must not drive on after a reset
    eases_in = True  # the hand holds it wherever it is: the robot goes there at joining speed
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
        #: An actuated leader's way to the follower's pose: (trio time, joint values), each
        #: as written to its servos.
        self.approach: list[tuple[float, dict[str, float]]] = []

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
            if self.config.actuated:
                await self._meet_follower(link, self.worker, self.bridge)
            await self._mirror(link, self.bridge)
        finally:
            await self.close()

    async def _meet_follower(self, link: MasterLink, worker: BusWorker, bridge: BusBridge) -> None:
        """Torque on, drive the leader to the follower's pose at the joining speed, torque
        off. Nothing is commanded meanwhile; a lost bus ends it (the mirror then reports it)."""
        snapshot = link.robot.snapshot()
        goal = {
            j.name: j.virtual_value if j.real_value is None else j.real_value
            for j in snapshot.joints
        }
        reading = bridge.take_reading()
        while reading is None:
            reading, events = await bridge.next()
            if any(isinstance(event, Lost) for event in events):
                return
        start = self._pose(reading)
        speed = self.model.safety.join_speed
        far = max(abs(goal[name] - value) for name, value in start.items())
        await wait_future(worker.submit(lambda bus: worker.hold(bus, torque=True)))
        began = trio.current_time()
        try:
            while True:
                now = trio.current_time()
                reach = speed * (now - began)
                pose = {
                    name: value + max(-reach, min(reach, goal[name] - value))
                    for name, value in start.items()
                }
                worker.set_goals(self.calibration.to_goal_steps(pose, self.spans))
                self.approach.append((now, pose))
                if reach >= far:
                    break
                await trio.sleep(1.0 / self.config.rate)
            # Let the servos get there (bounded: a leader held by a hand stops short).
            with trio.move_on_after(1.0):
                while not _near(self._pose(reading), goal, 1.0):
                    newer, _ = await bridge.next()
                    reading = newer or reading
        finally:
            with trio.CancelScope(shield=True):
                await wait_future(worker.submit(lambda bus: worker.hold(bus, torque=False)))
        log.info("usb-master on %s: at the follower's pose, limp", self.port)

    async def _mirror(self, link: MasterLink, bridge: BusBridge) -> None:
        interval = 1.0 / min(self.config.rate, self.model.safety.command_rate)
        last_sent: dict[str, float] | None = None
        last_at = -math.inf
        # The dead band's remainder: a pose held `SETTLE_AFTER` seconds (no joint further than
        # a quarter of the band from `still`) is sent once even when inside the band, so the
        # follower settles where the leader settled, not up to the band short of it.
        still: dict[str, float] | None = None
        still_since = -math.inf
        settled = False
        trend = _Trend()
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
            moving = trend.moving(reading.positions)
            pose = self._pose(reading)
            read_time = reading.time
            now = trio.current_time()
            if still is None or _moved(pose, still, self.config.deadband / 4):
                still, still_since, settled = pose, now, False
            if (
                last_sent is not None
                and not _moved(pose, last_sent, self.config.deadband)
                and not (moving and pose != last_sent)
            ):
                if settled or now - still_since < SETTLE_AFTER or pose == last_sent:
                    continue
                settled = True  # once: a hand's flicker afterwards sends nothing
            wait = last_at + interval - trio.current_time()
            if wait > 0:  # the robot's rate limit: wait, then send the newest pose there is
                await trio.sleep(wait)
                newer = bridge.take_reading()
                if newer is not None:
                    pose = self._pose(newer)
                    read_time = newer.time
            last_at = trio.current_time()
            # When the pose was read, on the robot's clock: the trajectory follows the
            # leader's stream by its read times, not by the loop's jitter of arrival.
            read_at = trio.current_time() - max(0.0, time.monotonic() - read_time)
            result = await link.command(
                Command(
                    tuple(JointGoal(n, v) for n, v in pose.items()),
                    source="leader-arm",
                    stamp=read_at,
                )
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


class _Trend:
    """Per servo, the way its raw reading last changed and how many changes in a row went
    that way: `moving` says when a reading takes a run to `TREND_CHANGES` or further."""

    def __init__(self) -> None:
        self._last: dict[int, int] = {}
        self._way: dict[int, int] = {}
        self._run: dict[int, int] = {}

    def moving(self, positions: Mapping[int, int]) -> bool:
        """Whether a servo's reading in `positions` went a step further in a run."""
        moving = False
        for sid, value in positions.items():
            last = self._last.get(sid)
            self._last[sid] = value
            if last is None or value == last:
                continue
            way = 1 if value > last else -1
            run = self._run.get(sid, 0) + 1 if way == self._way.get(sid) else 1
            self._way[sid], self._run[sid] = way, run
            moving = moving or run >= TREND_CHANGES
        return moving


def _near(pose: Mapping[str, float], goal: Mapping[str, float], tolerance: float) -> bool:
    """Whether every joint of `pose` is within `tolerance` of `goal`."""
    return all(abs(value - goal[name]) <= tolerance for name, value in pose.items())


def _moved(pose: Mapping[str, float], last: Mapping[str, float], deadband: float) -> bool:
    """Whether any joint moved more than `deadband` degrees since the last command."""
    return any(abs(value - last.get(name, math.inf)) > deadband for name, value in pose.items())
