"""`arena learn reach --dagger ROUNDS`: the loop that makes a policy better, whole, in the twin.

A few of the expert's demonstrations train a first policy. Each round deploys the newest policy
as the twin's master (a `PolicyMaster`, every master rule applying) on targets of its own, and a
scripted corrector, the task's expert, watches it: when the policy strays (no progress toward
the target for half a second) the corrector intervenes as a human would (the robot's
intervention: the policy paused, not ended; the corrector's commands eased in at the joining
speed), brings the tip to the target and hands back (the policy resumes from a fresh
observation, its first step within the step limit). Everything is recorded as a server
records it; Arena's own export writes the corrections as a LeRobot dataset (`intervention`
true on every frame, each correction an episode of its own, as `arena export
--corrections-only` does); they join the data and the policy is trained again. Held-out
success is measured after each round. specs/learning.md has the figures and the reasons.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from gymnasium.utils import seeding

from arena.gym.learn import (
    HELD_OUT_SEED,
    REPO_ID,
    TASK,
    LearnSettings,
    SharedWorker,
    collect,
)
from arena.gym.task import SUCCESS_DISTANCE, Expert, Reach, Success
from arena.gym.train import TrainSettings, train_act_on
from arena.gym.worlds import TWIN_ROBOT, TwinWorld, command_of
from arena.policy.master import PolicyMaster, PolicySettings
from arena.policy.process import PolicyProcess
from arena.recording.dataset import export_lerobot

#: The corrector's master id (the source of its commands in the recording).
CORRECTOR = "corrector"
#: The policy strays when its tip has come no closer than its best by `PROGRESS` metres for
#: `STRAY_SECONDS`, outside the success distance.
STRAY_SECONDS = 0.5
PROGRESS = 0.002
#: The corrector hands back once the tip is this close to the target (metres): well inside
#: the success distance, so what the policy resumes from is a pose it only has to hold.
HANDBACK_DISTANCE = 0.01
#: Seeds of the rollouts' targets start here (demonstrations use seed + 0, 1, ...; held-out
#: targets `HELD_OUT_SEED` + ...).
ROLLOUT_SEED = 500_000
#: Training steps of each round's policy (afresh, on all the data so far).
STEPS = 1500


@dataclass(frozen=True, slots=True)
class DaggerSettings:
    """`demos` expert demonstrations, then `rounds` rounds of `rollouts` corrected episodes;
    every policy trained for `steps` steps and scored on `targets` held-out targets."""

    out: Path
    rounds: int = 2
    demos: int = 10
    rollouts: int = 20
    steps: int = STEPS
    targets: int = 20
    fps: float = 30.0
    seed: int = 0
    robot_type: str = "so-arm100"
    dim_model: int = 64
    dim_feedforward: int = 256


@dataclass
class RoundReport:
    """One round: its policy's held-out success, what its deployment was corrected (for the
    next round), and the time it took (seconds by stage)."""

    round: int
    success: float = 0.0
    frames: int = 0  # trained on
    loss: float = float("nan")
    rollouts: int = 0  # episodes this round's policy was deployed on (the last has none)
    rollout_success: float = 0.0  # of them, reached with or without help
    corrected_episodes: int = 0
    interventions: int = 0
    correction_frames: int = 0  # exported, added to the next round's data
    seconds: dict[str, float] = field(default_factory=dict)
    policy_dir: str = ""


@dataclass
class DaggerReport:
    """Every round's report and the whole run's time."""

    rounds: list[RoundReport] = field(default_factory=list)
    demo_frames: int = 0
    seconds: float = 0.0


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
    """One episode of a policy in the twin: reached or not, and how it was corrected."""

    success: bool = False
    interventions: int = 0
    corrected_steps: int = 0


def target_of(task: Reach, seed: int) -> list[float]:
    """The target `ArenaEnv.reset(seed=seed)` draws (from Gymnasium's generator of `seed`)."""
    rng, _ = seeding.np_random(seed)
    return list(task.draw_target(rng))


async def deploy(
    world: TwinWorld,
    worker: SharedWorker,
    policy: Path,
    target: Sequence[float],
    max_steps: int,
    corrector: bool,
) -> Deployment:
    """Run `policy` as the twin's master toward `target` (the twin reset for it) for
    `max_steps` steps at most, until the tip holds there; with `corrector`, the expert
    intervenes whenever it strays and hands back once the tip is at the target."""
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
    steps = 0

    def reached() -> tuple[float, bool]:
        distance = task.distance(world.measured(), target)
        return distance, success.update(distance)

    try:
        while steps < max_steps:
            await world.advance(world.period)
            steps += 1
            distance, done = reached()
            if done:
                outcome.success = True
                break
            if not (corrector and stray.update(distance)):
                continue
            # The corrector intervenes: the policy is paused (its worker stays loaded), and
            # the corrector's commands are eased in at the joining speed.
            outcome.interventions += 1
            link = await robot.connect_master(
                CORRECTOR, kind="corrector", description="the reach task's expert", intervene=True
            )
            expert = Expert(task, target, world.measured(), follow=True)
            while steps < max_steps:
                await world.command(
                    command_of(world.model, expert.act(world.measured()).tolist()), link
                )
                await world.advance(world.period)
                steps += 1
                outcome.corrected_steps += 1
                distance, done = reached()
                if done or distance <= HANDBACK_DISTANCE:
                    break
            # Hand back: the policy resumes from a fresh observation (unless it is over).
            await robot.end_intervention(resume=not done)
            if done:
                outcome.success = True
                break
            stray.restart()
    finally:
        snapshot = robot.snapshot()
        if snapshot.paused_master is not None and snapshot.master is not None:
            await robot.end_intervention(resume=False)
        await robot.detach_master(reason="deployment over")
    return outcome


def held_out_success(
    world: TwinWorld, worker: SharedWorker, policy: Path, seeds: Sequence[int]
) -> float:
    """The policy's success rate alone (no corrector) on the targets of `seeds`."""
    task = Reach(world.model)
    max_steps = round(6.0 * world.fps)

    async def run(target: list[float]) -> bool:
        await world.reset_now(target)
        return (await deploy(world, worker, policy, target, max_steps, False)).success

    return float(np.mean([world.loop.call(run, target_of(task, seed)) for seed in seeds]))


def rollouts(
    world: TwinWorld,
    worker: SharedWorker,
    policy: Path,
    seeds: Sequence[int],
    report: RoundReport,
) -> dict[int, list[float]]:
    """The policy deployed on the targets of `seeds` with the corrector watching, each run an
    episode of the recording; the target of each episode by its recorded index."""
    task = Reach(world.model)
    max_steps = round(6.0 * world.fps)
    targets: dict[int, list[float]] = {}
    wins = []
    for seed in seeds:
        target = target_of(task, seed)

        async def run(target: list[float] = target) -> tuple[int, Deployment]:
            await world.reset_now(target)
            index = await world.episode_now("start", TASK)
            outcome = await deploy(world, worker, policy, target, max_steps, True)
            await world.episode_now("stop")
            return index, outcome

        index, outcome = world.loop.call(run)
        targets[index] = target
        wins.append(outcome.success)
        report.interventions += outcome.interventions
        report.corrected_episodes += outcome.interventions > 0
    report.rollouts = len(seeds)
    report.rollout_success = float(np.mean(wins)) if wins else 0.0
    return targets


def learn_dagger(settings: DaggerSettings, say: Callable[[str], None] = print) -> DaggerReport:
    """The whole loop; the report is also written to `out/report.json`."""
    out = settings.out
    out.mkdir(parents=True, exist_ok=True)
    report = DaggerReport()
    began = clock = time.perf_counter()

    def lap(stage: RoundReport, name: str) -> None:
        nonlocal clock
        now = time.perf_counter()
        stage.seconds[name] = round(now - clock, 1)
        clock = now

    first = RoundReport(0)
    say(
        f"collecting {settings.demos} expert demonstrations in the {settings.robot_type}'s twin ..."
    )
    demos = out / "demos"
    learn = LearnSettings(
        demos, settings.demos, fps=settings.fps, seed=settings.seed, robot_type=settings.robot_type
    )
    targets = collect(learn, say)
    if not targets:
        raise RuntimeError("the expert kept no demonstration")
    exported = export_lerobot(
        sorted((demos / "recordings").glob("*.mcap")),
        TWIN_ROBOT,
        demos / "dataset",
        fps=round(settings.fps),
        repo_id=REPO_ID,
        environment=targets,
        say=say,
    )
    report.demo_frames = sum(frames for _, _, frames in exported.episodes)
    datasets: list[tuple[Path, str]] = [(demos / "dataset", exported.repo_id)]
    lap(first, "collect")
    held_out = [HELD_OUT_SEED + settings.seed + k for k in range(settings.targets)]
    stage = first
    for number in range(settings.rounds + 1):
        folder = out / f"round-{number}"
        frames = report.demo_frames + sum(r.correction_frames for r in report.rounds)
        steps = settings.steps
        say(f"round {number}: training ACT for {steps} steps on {frames} frames ...")
        policy = folder / "policy"
        train = TrainSettings(
            steps=steps,
            dim_model=settings.dim_model,
            dim_feedforward=settings.dim_feedforward,
            seed=settings.seed,
        )
        stage.loss = train_act_on(datasets, policy, train, say)
        stage.frames, stage.policy_dir = frames, str(policy)
        lap(stage, "train")
        last = number == settings.rounds
        world = TwinWorld(
            settings.robot_type, settings.fps, recordings=None if last else folder / "recordings"
        )
        try:
            process = world.loop.call(PolicyProcess.start)
            worker = SharedWorker(process, world)
            try:
                stage.success = held_out_success(world, worker, policy, held_out)
                say(
                    f"round {number}: policy {stage.success:.0%} on {settings.targets} held-out "
                    f"targets ({frames} frames)"
                )
                lap(stage, "evaluate")
                if not last:
                    begin = ROLLOUT_SEED + settings.seed + number * settings.rollouts
                    seeds = range(begin, begin + settings.rollouts)
                    episodes = rollouts(world, worker, policy, seeds, stage)
            finally:
                world.loop.call(process.close)
        finally:
            world.close()
        report.rounds.append(stage)
        if last:
            break
        say(
            f"round {number}: deployed on {stage.rollouts} targets, reached "
            f"{stage.rollout_success:.0%}; the corrector intervened {stage.interventions} "
            f"times in {stage.corrected_episodes} of them"
        )
        if stage.interventions:
            corrections = export_lerobot(
                sorted((folder / "recordings").glob("*.mcap")),
                TWIN_ROBOT,
                folder / "corrections",
                fps=round(settings.fps),
                repo_id=f"{REPO_ID}-corrections-{number}",
                environment=episodes,
                corrections_only=True,
                say=say,
            )
            stage.correction_frames = sum(frames for _, _, frames in corrections.episodes)
            datasets.append((folder / "corrections", corrections.repo_id))
        lap(stage, "rollouts")
        stage = RoundReport(number + 1)
    report.seconds = round(time.perf_counter() - began, 1)
    record: dict[str, Any] = asdict(report) | {"settings": asdict(settings)}
    record["settings"]["out"] = str(out)
    (out / "report.json").write_text(json.dumps(record, indent=2), encoding="utf-8")
    return report
