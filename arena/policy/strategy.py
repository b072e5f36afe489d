"""Rollout strategies of a policy master, as LeRobot 0.6 names them (specs/policy.md, "Rollout
strategies"): the episodes a run makes, and when.

- `Episodic`: N episodes of T seconds with the task; between two, the policy is paused (its
  worker stays loaded) and the robot is taken back to a start pose at the robot's join speed,
  by commands of the policy's own identity through every rule; the master ends after the last.
- `Sentry`: the policy runs on; a new episode every T seconds.
- `Highlight`: nothing is an episode until `POST .../highlight`, which keeps the last N
  seconds as one. The recorder's side of it (what is kept in memory while it writes nothing,
  and written at a highlight) is a `Keeper`.

Episodes are the robot's own (`RobotView.episode`): recorded on `/robots/{id}/episode`,
exported by `arena export` as any other. Interventions during a strategy are tagged as always:
an intervention pauses the policy, the strategy's clock runs on.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Protocol

import trio

from arena.protocol.errors import ArenaError, ErrorCode
from arena.robot.episodes import Episode
from arena.robot.links import RobotView
from arena.robot.model import RobotModel
from arena.robot.motion import Command, CommandResult, JointGoal

log = logging.getLogger(__name__)

#: Degrees within which a joint counts as back at the start pose.
POSE_TOLERANCE = 1.0
#: Seconds the episode of a strategy that ends is given to be stopped (the robot may be gone).
_STOP_BOUND = 2.0


@dataclass(frozen=True, slots=True)
class Episodic:
    """`episodes` episodes of `episode_s` seconds; between two, `reset_s` seconds at most to
    take the robot back to `start_pose` (None: the pose at attach)."""

    episodes: int
    episode_s: float
    task: str
    reset_s: float = 10.0
    start_pose: Mapping[str, float] | None = None


@dataclass(frozen=True, slots=True)
class Sentry:
    """A new episode every `episode_s` seconds, for as long as the policy runs."""

    episode_s: float
    task: str


@dataclass(frozen=True, slots=True)
class Highlight:
    """The last `keep_s` seconds kept; `POST .../highlight` saves them as an episode."""

    keep_s: float
    task: str


Strategy = Episodic | Sentry | Highlight


class RolloutArm(Protocol):
    """The robot as the strategy commands it (the policy's `Arm`)."""

    def measured(self) -> tuple[float, ...]:
        """Each joint's measured value, Arena's units, in servo order."""

    async def command(self, command: Command) -> CommandResult:
        """Send one command as the master."""

    @property
    def paused(self) -> bool:
        """The robot has the master paused."""

    async def wait_resumed(self) -> None:
        """Return once the master is not paused."""


class Driven(Protocol):
    """What a strategy needs of its policy master (`PolicyMaster`)."""

    model: RobotModel

    @property
    def identity(self) -> str:
        """The source of its commands."""

    @property
    def fps(self) -> float:
        """Its control steps a second."""

    def report(self, code: ErrorCode, message: str) -> None:
        """A warning fault of the policy."""

    async def suspend(self) -> None:
        """Pause the policy; return once it holds."""

    def unsuspend(self) -> None:
        """Resume it from a fresh observation."""


class Keeper(Protocol):
    """The recorder's side of a highlight: while it writes nothing, it keeps the robot's last
    seconds in memory, and writes the kept part at a highlight."""

    def keep(self, seconds: float) -> None:
        """Keep this robot's last `seconds` from now on, whenever the recorder is off."""

    def release(self) -> None:
        """Keep nothing more (the strategy ended)."""

    async def save(self, since: float, until: float) -> None:
        """Make sure what happened from `since` to `until` (trio time) is written, with the
        marks of the episode just made."""


def check_pose(
    names: list[str], limits: Mapping[str, tuple[float, float]], pose: Mapping[str, float]
) -> None:
    """INVALID_VALUE unless each joint of `pose` is one of the robot's, with a finite value
    within its limits."""
    for name, value in pose.items():
        if name not in limits:
            raise ArenaError(
                ErrorCode.INVALID_VALUE,
                f'"start_pose" names {name!r}, which is no joint of this robot '
                f"({', '.join(names)}).",
            )
        lower, upper = limits[name]
        if not (math.isfinite(value) and lower <= value <= upper):
            raise ArenaError(
                ErrorCode.INVALID_VALUE,
                f'"start_pose" puts {name!r} at {value!r}, outside its limits '
                f"{lower:g} to {upper:g}.",
            )


class Rollout:
    """One strategy carried out for `master` on `robot` (through `arm`, the policy's view of
    it). `run` returns when the strategy is over (an episodic one after its last episode), so
    that the master ends; the episode it holds open is stopped on the way out."""

    def __init__(
        self,
        strategy: Strategy,
        master: Driven,
        robot: RobotView,
        arm: RolloutArm,
        keeper: Keeper | None = None,
    ) -> None:
        self.strategy = strategy
        self.master = master
        self.robot = robot
        self.arm = arm
        self.keeper = keeper
        self.episodes = 0  # episodes this strategy made
        self._open = False  # an episode of this strategy runs
        self._since = 0.0  # a highlight starts no earlier (the run's start, the last one's end)

    async def run(self) -> None:
        """Carry the strategy out."""
        try:
            if isinstance(self.strategy, Episodic):
                await self._episodic(self.strategy)
            elif isinstance(self.strategy, Sentry):
                await self._sentry(self.strategy)
            else:
                await self._highlight(self.strategy)
        finally:
            with trio.CancelScope(shield=True) as scope:
                scope.deadline = trio.current_time() + _STOP_BOUND
                await self._stop()
            if self.keeper is not None:
                self.keeper.release()

    async def _episodic(self, strategy: Episodic) -> None:
        names = [joint.name for joint in self.master.model.joints]
        pose = dict(strategy.start_pose or dict(zip(names, self.arm.measured(), strict=True)))
        for number in range(strategy.episodes):
            if number:
                await self.reset(pose, strategy.reset_s)
            await self._start(strategy.task)
            await trio.sleep(strategy.episode_s)
            await self._stop()
        log.info("policy %s: %d episodes done", self.master.identity, strategy.episodes)

    async def _sentry(self, strategy: Sentry) -> None:
        while True:
            await self._start(strategy.task)
            await trio.sleep(strategy.episode_s)
            await self._stop()

    async def _highlight(self, strategy: Highlight) -> None:
        self._since = trio.current_time()
        if self.keeper is not None:
            self.keeper.keep(strategy.keep_s)
        await trio.sleep_forever()

    async def highlight(self) -> Episode:
        """Save the last `keep_s` seconds (none before the run began or before the last
        highlight's end) as a kept episode; NO_HIGHLIGHT if this strategy keeps none."""
        strategy = self.strategy
        if not isinstance(strategy, Highlight):
            raise ArenaError(
                ErrorCode.NO_HIGHLIGHT,
                f"The robot's policy runs the {type(strategy).__name__.lower()} strategy, "
                'which keeps no highlight: attach it with {"strategy": {"type": "highlight", '
                "...}}.",
            )
        episode = await self.robot.highlight(strategy.task, strategy.keep_s, self._since)
        ended = episode.ended if episode.ended is not None else trio.current_time()
        self._since = ended
        self.episodes += 1
        if self.keeper is not None:
            await self.keeper.save(episode.started, ended)
        return episode

    async def _start(self, task: str) -> None:
        try:
            await self.robot.episode("start", task)
        except ArenaError as refusal:
            # Someone else's episode runs (started over REST): this one is not made.
            self.master.report(refusal.code, f"No episode was started: {refusal.message}")
            return
        self._open = True
        self.episodes += 1

    async def _stop(self) -> None:
        if not self._open:
            return
        self._open = False
        try:
            await self.robot.episode("stop")
        except ArenaError as refusal:  # stopped over REST meanwhile, or the robot is gone
            log.info("policy %s: episode not stopped: %s", self.master.identity, refusal)

    async def reset(self, pose: Mapping[str, float], within: float) -> None:
        """Pause the policy, take the robot to `pose` within `within` seconds, resume."""
        await self.master.suspend()
        try:
            with trio.move_on_after(within) as bound:
                await self.move_to(pose)
            if bound.cancelled_caught:
                self.master.report(
                    ErrorCode.POSE_NOT_REACHED,
                    f"The robot did not reach its start pose within {within:g} s; the next "
                    "episode starts from where it is.",
                )
        finally:
            self.master.unsuspend()

    async def move_to(self, pose: Mapping[str, float]) -> None:
        """Command the robot to `pose` at the robot's join speed, one step a control period,
        as the policy (every rule applies); return once every joint measures within
        `POSE_TOLERANCE` of it. An intervention meanwhile pauses it: it goes on from where
        the robot is once resumed."""
        model = self.master.model
        names = [joint.name for joint in model.joints]
        period = 1.0 / self.master.fps
        step = model.safety.join_speed * period
        while True:
            await self.arm.wait_resumed()
            targets = dict(zip(names, self.arm.measured(), strict=True))
            tick = trio.current_time()
            while not self.arm.paused:
                arrived = True
                for name, goal in pose.items():
                    left = goal - targets[name]
                    if abs(left) > step:
                        targets[name] += math.copysign(step, left)
                        arrived = False
                    else:
                        targets[name] = goal
                command = Command(
                    tuple(JointGoal(name, targets[name]) for name in pose),
                    source=self.master.identity,
                )
                result = await self.arm.command(command)
                if not result.accepted and result.code in (ErrorCode.ESTOPPED, ErrorCode.NOT_OWNER):
                    await trio.sleep_forever()  # the robot ends the master
                measured = dict(zip(names, self.arm.measured(), strict=True))
                if arrived and all(
                    abs(measured[name] - goal) <= POSE_TOLERANCE for name, goal in pose.items()
                ):
                    return
                tick += period
                await trio.sleep_until(tick)


def describe(strategy: Strategy | None) -> str:
    """The strategy in a few words, for the master's description."""
    if isinstance(strategy, Episodic):
        return f"episodic: {strategy.episodes} x {strategy.episode_s:g} s"
    if isinstance(strategy, Sentry):
        return f"sentry: an episode every {strategy.episode_s:g} s"
    if isinstance(strategy, Highlight):
        return f"highlight: the last {strategy.keep_s:g} s kept"
    return ""
