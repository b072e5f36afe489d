"""The robot as a running policy sees it (`Arm`: a master's link here, `LinkArm`; a master's
session over the API elsewhere, `arena.policy.remote`), and what the policy reports through it:
camera frames in, inference records out."""

from __future__ import annotations

import time as wallclock
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import NamedTuple, Protocol

import trio

from arena.policy.features import measured
from arena.protocol.errors import ErrorCode, Severity
from arena.robot.events import PolicyInferred
from arena.robot.links import MasterLink
from arena.robot.model import RobotModel
from arena.robot.motion import Command, CommandResult


class Shot(NamedTuple):
    """A camera's newest frame: its JPEG and when it was captured (trio time, this process)."""

    jpeg: bytes
    captured: float


#: The newest frame of each of the robot's cameras by name (None: no frame yet).
CameraFrames = Callable[[], Mapping[str, Shot | None]]


@dataclass(frozen=True, slots=True)
class Inference:
    """One inference as recorded on `/robots/{id}/policy` (`events.PolicyInferred`): the
    step its observation was taken at, the chunk's actions and those kept, the round trip
    and the worker's part of it, and the age of the oldest camera frame it carried
    (seconds; None without a camera)."""

    timestep: int
    chunk_size: int
    kept: int
    latency: float
    inference: float
    frame_age: float | None


class Arm(Protocol):
    """The robot as a running policy sees it: a master's link here (`LinkArm`), a master's
    session over the API on another machine (`arena.policy.remote`)."""

    def measured(self) -> tuple[float, ...]:
        """Each joint's measured value (else its target), Arena's units, in servo order."""

    async def command(self, command: Command) -> CommandResult:
        """Send one command as the master; its answer."""

    def fault(self, source: str, code: ErrorCode, message: str, severity: Severity) -> None:
        """Report a fault of the policy."""

    def inferred(self, source: str, inference: Inference) -> None:
        """Report one inference of the policy."""

    @property
    def paused(self) -> bool:
        """The robot has the policy paused: it sends nothing until resumed."""

    @property
    def pauses(self) -> int:
        """Times the robot has paused the policy so far (counted where the pause is made)."""

    async def wait_resumed(self) -> None:
        """Return once the policy is not paused."""


class LinkArm:
    """`Arm` over a master's link to a robot of this server."""

    def __init__(self, link: MasterLink, model: RobotModel) -> None:
        self.link = link
        self.model = model

    def measured(self) -> tuple[float, ...]:
        """See `Arm.measured`."""
        return measured(self.model, self.link.robot.snapshot())

    async def command(self, command: Command) -> CommandResult:
        """See `Arm.command`."""
        return await self.link.command(command)

    @property
    def paused(self) -> bool:
        """See `Arm.paused`."""
        return self.link.paused

    @property
    def pauses(self) -> int:
        """See `Arm.pauses`."""
        return self.link.pauses

    async def wait_resumed(self) -> None:
        """See `Arm.wait_resumed`."""
        await self.link.wait_resumed()

    def fault(self, source: str, code: ErrorCode, message: str, severity: Severity) -> None:
        """Recorded and shown as a camera's faults are; never an e-stop by itself."""
        self.link.robot.report_sensor_fault(source, code, message, severity)

    def inferred(self, source: str, inference: Inference) -> None:
        """Recorded on `/robots/{id}/policy`."""
        robot = self.link.robot
        robot.report_inference(
            PolicyInferred(
                robot.robot_id,
                source,
                inference.timestep,
                inference.chunk_size,
                inference.kept,
                inference.latency,
                inference.inference,
                inference.frame_age,
                trio.current_time(),
                wallclock.time(),
            )
        )
