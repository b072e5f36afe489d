"""`arena learn reach`: the whole loop in the twin. The scripted expert collects episodes through
Arena (recorded to MCAP, marked as episodes), `arena export --format lerobot`'s code makes the
dataset, LeRobot trains a small ACT on the CPU, and the policy runs as the twin's master (a
`PolicyMaster` with its worker process, every master rule applying) on targets it never saw.
Expert and random actions are scored on the same targets. specs/learning.md says why.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import trio

from arena.gym.env import ArenaEnv
from arena.gym.task import Expert, Success
from arena.gym.train import TrainSettings, train_act
from arena.gym.worlds import TWIN_ROBOT, TwinWorld
from arena.policy.master import PolicyMaster, PolicySettings
from arena.policy.process import PolicyProcess
from arena.policy.wire import Chunk, Loaded, Observe
from arena.recording.dataset import export_lerobot

#: The episodes' task, as the dataset names it.
TASK = "reach the target"
REPO_ID = "arena/reach"
#: Seeds of the held-out targets start here (collection uses 0, 1, ...).
HELD_OUT_SEED = 1_000_000


@dataclass(frozen=True, slots=True)
class LearnSettings:
    """What `arena learn reach` does: `episodes` collected by the expert, `steps` of training,
    `targets` held out to evaluate on."""

    out: Path
    episodes: int = 50
    steps: int = 3000
    targets: int = 20
    fps: float = 30.0
    seed: int = 0
    robot_type: str = "so-arm100"


@dataclass
class LearnReport:
    """Success rates on the held-out targets, and where the time went (seconds)."""

    expert: float = 0.0
    random: float = 0.0
    policy: float = 0.0
    episodes: int = 0  # kept for the dataset
    frames: int = 0
    loss: float = float("nan")
    seconds: dict[str, float] = field(default_factory=dict)
    policy_dir: str = ""


def _run_expert(env: ArenaEnv, seed: int) -> bool:
    _, info = env.reset(seed=seed)
    expert = Expert(env.task, env.target, info["measured"])
    while True:
        action = env.to_action(expert.act(info["measured"]))
        _, _, terminated, truncated, info = env.step(action)
        if terminated or truncated:
            return bool(info["is_success"])


def _run_random(env: ArenaEnv, seed: int) -> bool:
    env.reset(seed=seed)
    env.action_space.seed(seed)
    while True:
        _, _, terminated, truncated, info = env.step(env.action_space.sample())
        if terminated or truncated:
            return bool(info["is_success"])


def collect(settings: LearnSettings, say: Callable[[str], None]) -> dict[int, list[float]]:
    """The expert's episodes, recorded in `out/recordings`; the target of each kept episode by
    its recorded index (a failed one is discarded, as an operator would)."""
    world = TwinWorld(settings.robot_type, settings.fps, recordings=settings.out / "recordings")
    env = ArenaEnv(world=world)
    targets: dict[int, list[float]] = {}
    try:
        for number in range(settings.episodes):
            _, info = env.reset(seed=settings.seed + number)
            index = world.loop.call(world.episode_now, "start", TASK)
            expert = Expert(env.task, env.target, info["measured"])
            while True:
                action = env.to_action(expert.act(info["measured"]))
                _, _, terminated, truncated, info = env.step(action)
                if terminated or truncated:
                    break
            if info["is_success"]:
                world.loop.call(world.episode_now, "stop")
                targets[index] = list(env.target)
            else:
                world.loop.call(world.episode_now, "discard")
            if (number + 1) % 10 == 0:
                say(f"  {number + 1}/{settings.episodes} episodes ({len(targets)} kept)")
    finally:
        env.close()
    return targets


class SharedWorker:
    """One policy worker for every run of the policy on the held-out targets: loaded once,
    left running when a run ends, and thinking in no time of the twin's (its clock stands
    still while the worker answers)."""

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
        """Nothing: the worker outlives each run (`evaluate` stops it)."""


async def _policy_episode(
    world: TwinWorld, env: ArenaEnv, worker: SharedWorker, policy: Path, target: list[float]
) -> bool:
    await world.reset_now(target)
    settings = PolicySettings(policy, task=TASK, fps=env.fps, environment_state=tuple(target))

    async def start() -> SharedWorker:
        return worker

    master = PolicyMaster(settings, world.model, dict, start_worker=start)
    await master.prepare()
    await world.robot.attach_master(master, takeover=True)
    success = Success(env.fps)
    try:
        for _ in range(env.max_steps):
            await world.advance(world.period)
            if success.update(env.task.distance(world.measured(), target)):
                return True
        return False
    finally:
        await world.robot.detach_master(reason="evaluation episode over")


def evaluate(settings: LearnSettings, policy: Path | None) -> dict[str, float]:
    """Success rates of the expert, random actions and (if given) the policy on the held-out
    targets."""
    world = TwinWorld(settings.robot_type, settings.fps)
    env = ArenaEnv(world=world)
    seeds = [HELD_OUT_SEED + settings.seed + k for k in range(settings.targets)]
    rates: dict[str, float] = {}
    try:
        rates["expert"] = float(np.mean([_run_expert(env, seed) for seed in seeds]))
        rates["random"] = float(np.mean([_run_random(env, seed) for seed in seeds]))
        if policy is not None:
            targets = []
            for seed in seeds:
                env.reset(seed=seed)
                targets.append(list(env.target))
            process = world.loop.call(PolicyProcess.start)
            worker = SharedWorker(process, world)
            try:
                wins = [
                    world.loop.call(_policy_episode, world, env, worker, policy, target)
                    for target in targets
                ]
            finally:
                world.loop.call(process.close)
            rates["policy"] = float(np.mean(wins))
    finally:
        env.close()
    return rates


def learn_reach(settings: LearnSettings, say: Callable[[str], None] = print) -> LearnReport:
    """The whole loop; the report is also written to `out/report.json`."""
    report = LearnReport()
    out = settings.out
    out.mkdir(parents=True, exist_ok=True)
    clock = time.perf_counter()

    def lap(name: str) -> None:
        nonlocal clock
        now = time.perf_counter()
        report.seconds[name] = round(now - clock, 1)
        clock = now

    say(f"collecting {settings.episodes} expert episodes in the twin ...")
    targets = collect(settings, say)
    report.episodes = len(targets)
    lap("collect")
    if not targets:
        raise RuntimeError("the expert kept no episode")
    say("exporting the recording as a LeRobot dataset ...")
    exported = export_lerobot(
        sorted((out / "recordings").glob("*.mcap")),
        TWIN_ROBOT,
        out / "dataset",
        fps=round(settings.fps),
        repo_id=REPO_ID,
        environment=targets,
        say=say,
    )
    report.frames = sum(frames for _, _, frames in exported.episodes)
    lap("export")
    say(f"training ACT for {settings.steps} steps on {report.frames} frames (CPU) ...")
    policy = out / "policy"
    train = TrainSettings(steps=settings.steps, seed=settings.seed)
    report.loss = train_act(out / "dataset", REPO_ID, policy, train, say)
    report.policy_dir = str(policy)
    lap("train")
    say(f"evaluating on {settings.targets} held-out targets ...")
    rates = evaluate(settings, policy)
    report.expert, report.random, report.policy = rates["expert"], rates["random"], rates["policy"]
    lap("evaluate")
    record: dict[str, Any] = asdict(report) | {"settings": asdict(replace(settings, out=Path()))}
    record["settings"]["out"] = str(out)
    (out / "report.json").write_text(json.dumps(record, indent=2), encoding="utf-8")
    return report
