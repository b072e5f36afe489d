"""`arena learn reach`: the whole loop in the twin. The scripted expert collects episodes through
Arena (recorded to MCAP, marked as episodes), `arena export --format lerobot`'s code makes the
dataset, LeRobot trains a small ACT on the CPU, and the policy runs as the twin's master (a
`PolicyMaster` with its worker process, every master rule applying) on targets it never saw.
Expert and random actions are scored on the same targets. specs/learning.md says why.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from arena.gym.deploy import TASK, policy_success
from arena.gym.env import ArenaEnv
from arena.gym.task import Expert
from arena.gym.train import TrainSettings, train_act
from arena.gym.worlds import TWIN_ROBOT, TwinWorld
from arena.recording.dataset import ExportReport, export_lerobot

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


def export_episodes(
    recordings: Path,
    root: Path,
    fps: float,
    repo_id: str,
    targets: Mapping[int, Sequence[float]],
    say: Callable[[str], None],
    **options: Any,
) -> ExportReport:
    """Arena's export (what `arena export --format lerobot` runs) of the twin's recordings in
    `recordings` to `root`, each episode's target as its environment state; `options` are
    `export_lerobot`'s."""
    return export_lerobot(
        sorted(recordings.glob("*.mcap")),
        TWIN_ROBOT,
        root,
        fps=round(fps),
        repo_id=repo_id,
        environment=targets,
        say=say,
        **options,
    )


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
            rates["policy"] = policy_success(world, policy, targets, env.max_steps)
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
    exported = export_episodes(
        out / "recordings", out / "dataset", settings.fps, REPO_ID, targets, say
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
