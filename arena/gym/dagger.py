"""`arena learn reach --dagger ROUNDS`: the loop that makes a policy better, whole, in the twin.

A few of the expert's demonstrations train a first policy. Each round deploys the newest policy
as the twin's master (`arena.gym.deploy`: a `PolicyMaster`, every master rule applying) on
targets of its own, with the task's expert watching as a corrector: when the policy strays (no
progress toward the target for half a second) it intervenes as a human would (the robot's
intervention: the policy paused, not ended; the corrector's commands eased in at the joining
speed) and hands back once the tip has held at the target. Everything is recorded as a server
records it, and Arena's own export writes the deployments as a LeRobot dataset (`intervention`
true on the corrector's frames). DAgger's labels: every frame, the policy's own too, is
trained on with the action the expert takes from that frame's state (`expert_labels`: the
corrector's very function, so its frames keep their commands), its sag compensation learned
per target in the twin and held fixed (`Compensation`). The data grows by each round's
relabelled deployments and the policy is trained again; held-out success is measured after
each round. specs/learning.md has the figures and the reasons.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from gymnasium.utils import seeding

from arena.gym.deploy import (
    CORRECTOR,
    TASK,
    SharedWorker,
    Stray,
    deploy,
    policy_worker,
    success_rate,
)
from arena.gym.learn import HELD_OUT_SEED, REPO_ID, LearnSettings, collect, export_episodes
from arena.gym.task import Expert, Reach
from arena.gym.train import Relabel, Source, TrainSettings, train_act_on
from arena.gym.worlds import TwinWorld, command_of
from arena.recording.dataset import ENVIRONMENT, INTERVENTION, from_dataset, to_dataset
from arena.robot.model import RobotModel

__all__ = ["CORRECTOR", "ROLLOUT_SEED", "STEPS", "DaggerSettings", "Stray", "learn_dagger"]

#: Seeds of the rollouts' targets start here (demonstrations use seed + 0, 1, ...; held-out
#: targets `HELD_OUT_SEED` + ...).
ROLLOUT_SEED = 500_000
#: Training steps of the first policy; every later round's policy (afresh, on all the data so
#: far) trains twice as many.
STEPS = 1500
#: Corrected deployments a round: each is a target the next policy learns from (a deployment
#: costs a few seconds of CPU, a round's training a minute and more).
ROLLOUTS = 50
#: An episode's longest run (seconds), deployed or evaluated.
EPISODE_SECONDS = 6.0
#: Steps the expert runs from rest to learn its sag compensation at a target (3 s at 30 fps:
#: its integral term has settled long before).
SETTLE_STEPS = 90


@dataclass(frozen=True, slots=True)
class DaggerSettings:
    """`demos` expert demonstrations, then `rounds` rounds of `rollouts` corrected episodes;
    every policy trained for `steps` steps and scored on `targets` held-out targets."""

    out: Path
    rounds: int = 2
    demos: int = 10
    rollouts: int = ROLLOUTS
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
    rollout_frames: int = 0  # exported, relabelled, added to the next round's data
    correction_frames: int = 0  # of them, the corrector's (`intervention` true)
    seconds: dict[str, float] = field(default_factory=dict)  # wall, by stage
    cpu_seconds: dict[str, float] = field(default_factory=dict)  # CPU (the worker's too)
    policy_dir: str = ""


@dataclass
class DaggerReport:
    """Every round's report and the whole run's time."""

    rounds: list[RoundReport] = field(default_factory=list)
    demo_frames: int = 0
    seconds: float = 0.0  # wall
    cpu_seconds: float = 0.0
    load_average: tuple[float, float, float] = (0.0, 0.0, 0.0)  # the machine's, at the end


def target_of(task: Reach, seed: int) -> list[float]:
    """The target `ArenaEnv.reset(seed=seed)` draws (from Gymnasium's generator of `seed`)."""
    rng, _ = seeding.np_random(seed)
    return list(task.draw_target(rng))


def target_key(target: Sequence[float]) -> tuple[float, ...]:
    """A target as a dataset holds it (float32), to look it up by a frame's."""
    return tuple(float(np.float32(value)) for value in target)


class Compensation:
    """The expert's sag compensation by target: the bias its integral term settles on when it
    reaches the target from rest in the twin (the arm sags under gravity by an amount that
    depends on the pose, which kinematics cannot know). The expert that corrects and labels
    holds it fixed from the first frame, so its action is a function of the state and the
    target alone; with the integral running, the same state got a different label the longer
    the arm had lingered off the target (a policy that stops 3 cm short winds it up toward
    its clip): labels that disagree, for a policy to average."""

    def __init__(self) -> None:
        self.biases: dict[tuple[float, ...], list[float]] = {}

    async def learn(self, world: TwinWorld, target: Sequence[float]) -> list[float]:
        """The compensation at `target`, learned in `world` if not known yet (the world is
        reset for it: the caller resets it again for its own run)."""
        key = target_key(target)
        if key not in self.biases:
            task = Reach(world.model)
            measured = await world.reset_now(target)
            expert = Expert(task, target, measured, follow=True)
            for _ in range(SETTLE_STEPS):
                action = expert.act(world.measured())
                await world.command(command_of(world.model, action.tolist()))
                await world.advance(world.period)
            self.biases[key] = [round(float(value), 6) for value in expert.bias]
        return self.biases[key]

    async def learn_all(self, world: TwinWorld, targets: Sequence[Sequence[float]]) -> None:
        """`learn` for each of `targets`."""
        for target in targets:
            await self.learn(world, target)

    def __call__(self, target: Sequence[float]) -> list[float]:
        """The compensation at a target learned before (a `KeyError` otherwise)."""
        return self.biases[target_key(target)]


def expert_labels(
    model: RobotModel, bias_of: Callable[[Sequence[float]], Sequence[float]] | None = None
) -> Relabel:
    """DAgger's labels: for each frame of a dataset's episodes, the action the task's expert
    takes from that frame's state, the expert having followed the episode from its first
    frame (`Expert(follow=True)`, the corrector's very function: on frames it commanded, the
    label is its command). The policy's own frames get what the expert would have done there,
    not what the policy did."""
    task = Reach(model)
    joints = model.joints

    def relabel(columns: dict[str, Any]) -> Any:
        states, targets = columns["observation.state"], columns[ENVIRONMENT]
        episodes = columns["episode_index"]
        labels = np.empty((len(states), len(joints)), dtype=np.float32)
        expert, episode = None, None
        for row, state in enumerate(states):
            measured = [from_dataset(j, float(v)) for j, v in zip(joints, state, strict=True)]
            if expert is None or episodes[row] != episode:
                bias = None if bias_of is None else bias_of(targets[row])
                expert = Expert(task, targets[row], measured, follow=True, bias=bias)
                episode = episodes[row]
            action = expert.act(measured)
            labels[row] = [to_dataset(j, float(v)) for j, v in zip(joints, action, strict=True)]
        return labels

    return relabel


async def rollouts(
    world: TwinWorld,
    worker: SharedWorker,
    policy: Path,
    seeds: Sequence[int],
    report: RoundReport,
    compensation: Compensation,
) -> dict[int, list[float]]:
    """The policy deployed on the targets of `seeds` with the corrector watching (its sag
    compensation learned first), each run an episode of the recording; the target of each
    episode by its recorded index."""
    task = Reach(world.model)
    max_steps = round(EPISODE_SECONDS * world.fps)
    targets: dict[int, list[float]] = {}
    wins = 0
    for seed in seeds:
        target = target_of(task, seed)
        bias = await compensation.learn(world, target)
        await world.reset_now(target)
        index = await world.episode_now("start", TASK)
        outcome = await deploy(world, worker, policy, target, max_steps, corrector=True, bias=bias)
        await world.episode_now("stop")
        targets[index] = target
        wins += outcome.success
        report.interventions += outcome.interventions
        report.corrected_episodes += outcome.interventions > 0
    report.rollouts = len(seeds)
    report.rollout_success = wins / len(seeds) if seeds else 0.0
    return targets


async def evaluate_and_deploy(
    world: TwinWorld,
    policy: Path,
    goals: Sequence[Sequence[float]],
    seeds: Sequence[int],
    stage: RoundReport,
    clock: Clock,
    say: Callable[[str], None],
    compensation: Compensation,
) -> dict[int, list[float]]:
    """A round's policy: its held-out success on `goals`, then its corrected deployments on
    the targets of `seeds` (if any), in one policy worker."""
    max_steps = round(EPISODE_SECONDS * world.fps)
    async with policy_worker(world) as worker:
        stage.success = await success_rate(world, worker, policy, goals, max_steps)
        say(
            f"round {stage.round}: policy {stage.success:.0%} on {len(goals)} held-out "
            f"targets ({stage.frames} frames)"
        )
        clock.lap(stage, "evaluate")
        if not seeds:
            return {}
        return await rollouts(world, worker, policy, seeds, stage, compensation)


class Clock:
    """Wall and CPU seconds (this process and its finished children: the policy's worker)
    by stage."""

    def __init__(self) -> None:
        self.began = self.wall = time.perf_counter()
        self.cpu = self._cpu()

    @staticmethod
    def _cpu() -> float:
        times = os.times()
        return times.user + times.system + times.children_user + times.children_system

    def lap(self, stage: RoundReport, name: str) -> None:
        """The time since the last lap, as `stage`'s `name`."""
        wall, cpu = time.perf_counter(), self._cpu()
        stage.seconds[name] = round(wall - self.wall, 1)
        stage.cpu_seconds[name] = round(cpu - self.cpu, 1)
        self.wall, self.cpu = wall, cpu


def learn_dagger(settings: DaggerSettings, say: Callable[[str], None] = print) -> DaggerReport:
    """The whole loop; the report is also written to `out/report.json`."""
    out = settings.out
    out.mkdir(parents=True, exist_ok=True)
    report = DaggerReport()
    clock = Clock()
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
    exported = export_episodes(
        demos / "recordings", demos / "dataset", settings.fps, REPO_ID, targets, say
    )
    report.demo_frames = sum(frames for _, _, frames in exported.episodes)
    compensation = Compensation()
    world = TwinWorld(settings.robot_type, settings.fps)
    try:
        world.loop.call(compensation.learn_all, world, list(targets.values()))
    finally:
        world.close()
    relabel = expert_labels(world.model, compensation)
    datasets: list[Source] = [(demos / "dataset", exported.repo_id, relabel)]
    clock.lap(first, "collect")
    goals: list[list[float]] = []
    held_out = [HELD_OUT_SEED + settings.seed + k for k in range(settings.targets)]
    stage = first
    frames = report.demo_frames
    for number in range(settings.rounds + 1):
        folder = out / f"round-{number}"
        # The first policy learns from a few hundred frames; the later ones from thousands,
        # of states the policy reached: twice the steps (1500 more: 90 % against 85 % on one
        # round's data, specs/learning.md).
        steps = settings.steps if number == 0 else 2 * settings.steps
        say(f"round {number}: training ACT for {steps} steps on {frames} frames ...")
        policy = folder / "policy"
        train = TrainSettings(
            steps=steps,
            dim_model=settings.dim_model,
            dim_feedforward=settings.dim_feedforward,
            dropout=0.0,  # the labels are one function of the state: nothing to average out
            seed=settings.seed,
        )
        stage.loss = train_act_on(datasets, policy, train, say)
        stage.frames, stage.policy_dir = frames, str(policy)
        clock.lap(stage, "train")
        last = number == settings.rounds
        world = TwinWorld(
            settings.robot_type, settings.fps, recordings=None if last else folder / "recordings"
        )
        goals = goals or [target_of(Reach(world.model), seed) for seed in held_out]
        begin = ROLLOUT_SEED + settings.seed + number * settings.rollouts
        seeds = range(begin, 0 if last else begin + settings.rollouts)
        try:
            episodes = world.loop.call(
                evaluate_and_deploy, world, policy, goals, seeds, stage, clock, say, compensation
            )
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
        deployed = export_episodes(
            folder / "recordings",
            folder / "rollouts",
            settings.fps,
            f"{REPO_ID}-rollouts-{number}",
            episodes,
            say,
        )
        stage.rollout_frames = sum(count for _, _, count in deployed.episodes)
        stage.correction_frames = intervention_frames(folder / "rollouts", deployed.repo_id)
        datasets.append((folder / "rollouts", deployed.repo_id, relabel))
        frames += stage.rollout_frames
        clock.lap(stage, "rollouts")
        stage = RoundReport(number + 1)
    report.seconds = round(time.perf_counter() - clock.began, 1)
    report.cpu_seconds = round(sum(sum(r.cpu_seconds.values()) for r in report.rounds), 1)
    report.load_average = os.getloadavg()
    record: dict[str, Any] = asdict(report) | {"settings": asdict(settings)}
    record["compensation"] = [[list(key), bias] for key, bias in compensation.biases.items()]
    record["settings"]["out"] = str(out)
    (out / "report.json").write_text(json.dumps(record, indent=2), encoding="utf-8")
    return report


def intervention_frames(root: Path, repo_id: str) -> int:
    """How many frames of the dataset at `root` the corrector commanded."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    table = LeRobotDataset(repo_id, root=root).hf_dataset.with_format("numpy")
    if INTERVENTION not in table.column_names:
        return 0
    return int(np.asarray(table[INTERVENTION]).sum())
