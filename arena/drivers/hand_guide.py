"""Hand guiding: a person moves the arm, and the robot records it as a master's commands.

`POST /api/robots/{id}/compliance` lowers the torque of some joints of the robot's usb-slave
(`UsbSlave.enter_compliance`, refused there if a servo cannot be limited) and attaches this
master: it reads the arm's measured pose and
commands the robot with the compliant joints' values (`source: "hand-guide"`) whenever one moved
more than the dead band, at most at the robot's command rate, so the robot's target follows
the hand (the servo, given that target, no longer pulls back) and the motion is recorded, replays
and exports as teleoperation does (kinesthetic teaching). It ends (`DELETE .../compliance`, an
e-stop, a refusal) by leaving compliance: the arm holds where it is. specs/force.md.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Protocol

import trio

from arena.protocol.errors import ErrorCode
from arena.robot.links import MasterLink
from arena.robot.motion import Command, JointGoal

#: Refusals after which hand guiding ends for good.
_FINAL_REFUSALS = frozenset({ErrorCode.ESTOPPED, ErrorCode.NOT_OWNER})
SOURCE = "hand-guide"


class Compliant(Protocol):
    """The arm a hand guides (a `UsbSlave`)."""

    pose: dict[str, float]

    async def leave_compliance(self) -> None: ...


class HandGuide:
    """A master that turns the measured motion of `joints` of `arm` into commands."""

    kind = "hand-guide"
    autonomous = True  # an e-stop ends it: nobody guides an e-stopped arm
    takes_over = False

    def __init__(
        self,
        arm: Compliant,
        joints: Sequence[str],
        torque: float,
        command_rate: float,
        deadband: float = 0.5,
    ) -> None:
        self.arm = arm
        self.joints = tuple(joints)
        self.torque = torque
        self.interval = 1.0 / command_rate
        self.deadband = deadband
        self.sent = 0

    @property
    def description(self) -> str:
        """What it is, in words."""
        return f"hand guiding of {', '.join(self.joints)} at {self.torque:g} % torque"

    async def run(self, link: MasterLink) -> None:
        """The hand's motion as commands until detached or refused; then compliance ends."""
        try:
            last: dict[str, float] | None = None
            while True:
                await trio.sleep(self.interval)
                pose = {n: v for n, v in self.arm.pose.items() if n in self.joints}
                if not pose or (last is not None and not _moved(pose, last, self.deadband)):
                    continue
                result = await link.command(
                    Command(tuple(JointGoal(n, v) for n, v in pose.items()), source=SOURCE)
                )
                self.sent += 1
                if result.accepted:
                    last = pose
                elif result.code in _FINAL_REFUSALS:
                    return
        finally:
            with trio.CancelScope(shield=True):
                await self.arm.leave_compliance()


def _moved(pose: Mapping[str, float], last: Mapping[str, float], deadband: float) -> bool:
    return any(abs(value - last.get(name, math.inf)) > deadband for name, value in pose.items())
