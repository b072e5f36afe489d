"""A trained policy run as the twin's master, the one piece `arena learn reach` evaluates with
and `--dagger` deploys with: a `PolicyMaster` (every master rule applying) fed by one shared
worker, on a target the twin was reset for, until the tip holds there or time is up. With an
expert watching, the expert follows the arm every step (what it would command from each
state the policy reaches), and, as a corrector, intervenes through the robot's intervention
calls when the policy strays, handing back once the tip has held at the target.
"""

from __future__ import annotations

import math
from collections.abc import AsyncIterator, Sequence
from contextlib import asynccontextmanager
from dataclasses import dataclass
from pathlib import Path

import trio

from arena.gym.task import SUCCESS_DISTANCE, Expert, Reach, Success
from arena.gym.worlds import TwinWorld, command_of
from arena.policy.master import PolicyMaster, PolicySettings
from arena.policy.process import PolicyProcess
from arena.policy.wire import Chunk, Loaded, Observe

#: The episodes' task, as the dataset names it.
TASK = "reach the target"
#: The corrector's master id (the source of its commands in the recording).
CORRECTOR = "corrector"
#: The policy strays when its tip has come no closer than its best by `PROGRESS` metres for
#: `STRAY_SECONDS`, outside the success distance.
STRAY_SECONDS = 0.5
PROGRESS = 0.002
#: The corrector hands back once the tip has stayed within `HANDBACK_DISTANCE` (metres) of
#: the target for `HANDBACK_SECONDS`: the policy resumes on a pose it only has to hold (it
#: must hold it on its own for the rest of the success hold).
HANDBACK_DISTANCE = 0.01
HANDBACK_SECONDS = 1 / 3


class SharedWorker:
    """One policy worker for every run of the policy: loaded once, left running when a run
    ends, and thinking in no time of the twin's (its clock stands still while the worker
    answers)."""

    def __init__(self, process: PolicyProcess, world: TwinWorld) -> None:
        self.process = process
        self.world = world
        self.loaded: Loaded | None = None
        self._one_at_a_time = trio.Lock()

    async def load(self, path: Path) -> Loaded:
        """The policy, loaded on the first call."""
        if self.loaded is None:
            self.loaded = await self.process.load(path)
        return self.loaded

    async def act(self, observation: Observe) -> Chunk:
        """The worker's chunk, the twin's clock standing still meanwhile. A run that ends
        waits for the answer in flight: a request abandoned half-way ends a worker's use (the
        next run's would find the pipe out of step), and the answer takes milliseconds."""
        with trio.CancelScope(shield=True):
            async with self._one_at_a_time, self.world.standing_still():
                chunk = await self.process.act(observation)
        return chunk

    async def close(self) -> None:
        """Nothing: the worker outlives each run (`policy_worker` stops it)."""


@asynccontextmanager
async def policy_worker(world: TwinWorld) -> AsyncIterator[SharedWorker]:
    """A policy worker process for `world`'s runs, stopped when the block ends."""
    process = await PolicyProcess.start()
    try:
        yield SharedWorker(process, world)
    finally:
        await process.close()


class Stray:
    """Whether the policy strays: its tip has come no closer to the target than its best by
    `PROGRESS` for `STRAY_SECONDS`, and is not within the success distance (holding there is
    what it should do)."""

    def __init__(self, fps: float) -> None:
        self.window = max(1, math.ceil(STRAY_SECONDS * fps))
        self.best = math.inf
        self.since = 0

    def restart(self) -> None:
        """Watch afresh (the policy has the robot again)."""
        self.best, self.since = math.inf, 0

    def update(self, distance: float) -> bool:
        """One step at `distance` (metres); True when the policy strays."""
        if distance < self.best - PROGRESS:
            self.best, self.since = distance, 0
        else:
            self.since += 1
        return distance > SUCCESS_DISTANCE and self.since >= self.window


@dataclass
class Deployment:
    """One run of a policy in the twin: reached or not, and how it was corrected."""

    success: bool = False
    steps: int = 0
    interventions: int = 0
    corrected_steps: int = 0


async def deploy(
    world: TwinWorld,
    worker: SharedWorker,
    policy: Path,
    target: Sequence[float],
    max_steps: int,
    corrector: bool = False,
    bias: Sequence[float] | None = None,
) -> Deployment:
    """Run `policy` as the twin's master toward `target` (the twin just reset for it) for
    `max_steps` steps at most, until the tip holds there. With `corrector`, the task's expert
    watches from the start: it follows the arm every step (`Expert(follow=True)`, so its
    action is the same function of what it has seen whoever drives), and when the policy
    strays it intervenes, commanding those actions, and hands back after a hold. `bias`: the
    expert's sag compensation at the target, held fixed (`Expert`'s `bias`)."""
    task = Reach(world.model)
    fps = world.fps
    settings = PolicySettings(policy, task=TASK, fps=fps, environment_state=tuple(target))

    async def start() -> SharedWorker:
        return worker

    master = PolicyMaster(settings, world.model, dict, start_worker=start)
    await master.prepare()
    robot = world.robot
    await robot.attach_master(master, takeover=True)
    outcome, success, stray = Deployment(), Success(fps), Stray(fps)
    handback = max(1, math.ceil(HANDBACK_SECONDS * fps))
    measured = world.measured()
    expert = Expert(task, target, measured, follow=True, bias=bias) if corrector else None
    link, held = None, 0
    try:
        while outcome.steps < max_steps:
            # The expert sees every frame's state in order (its plan follows the arm): what
            # it commands when correcting is what it would have done from any state before.
            action = None if expert is None else expert.act(measured)
            if link is not None and action is not None:
                await world.command(command_of(world.model, action.tolist()), link)
                outcome.corrected_steps += 1
            await world.advance(world.period)
            outcome.steps += 1
            measured = world.measured()
            distance = task.distance(measured, target)
            if success.update(distance):
                outcome.success = True
                break
            if link is not None:
                held = held + 1 if distance <= HANDBACK_DISTANCE else 0
                if held >= handback:  # hand back: the policy resumes from a fresh observation
                    await robot.end_intervention(resume=True)
                    link = None
                    stray.restart()
            elif corrector and stray.update(distance):
                # The corrector intervenes: the policy is paused (its worker stays loaded),
                # and the corrector's commands are eased in at the joining speed.
                outcome.interventions += 1
                link = await robot.connect_master(
                    CORRECTOR,
                    kind="corrector",
                    description="the reach task's expert",
                    intervene=True,
                )
                held = 0
    finally:
        snapshot = robot.snapshot()
        if snapshot.paused_master is not None and snapshot.master is not None:
            await robot.end_intervention(resume=False)
        await robot.detach_master(reason="deployment over")
    return outcome


async def success_rate(
    world: TwinWorld,
    worker: SharedWorker,
    policy: Path,
    targets: Sequence[Sequence[float]],
    max_steps: int,
) -> float:
    """The policy's success rate alone (no corrector) on `targets`, `max_steps` steps each."""
    wins = 0
    for target in targets:
        await world.reset_now(target)
        wins += (await deploy(world, worker, policy, target, max_steps)).success
    return wins / len(targets) if targets else 0.0


def policy_success(
    world: TwinWorld, policy: Path, targets: Sequence[Sequence[float]], max_steps: int
) -> float:
    """`success_rate` in a worker of its own."""

    async def run() -> float:
        async with policy_worker(world) as worker:
            return await success_rate(world, worker, policy, targets, max_steps)

    return world.loop.call(run)
