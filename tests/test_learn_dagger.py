"""`arena learn reach --dagger`, small enough for CI: on the so-101, two demonstrations, a policy
trained a few steps (so it strays), one round of corrected deployments. The mechanics, each read
back by its own reader: the corrector intervened through the robot's intervention (its start and
end in the recording, its commands accepted under its own id), Arena's export wrote its
corrections with `intervention` and the episode's target (LeRobot's own `LeRobotDataset`
reads them), the next round trained on more frames, and the retrained policy is loaded by a
server's policy master as a user would load it. The success figures are the long run's
(specs/learning.md), not this test's."""

from __future__ import annotations

import json
import os
import sys
from collections.abc import Awaitable, Callable
from pathlib import Path

import httpx
import numpy as np
import trio

from arena.recording.mcap_file import read_recording
from arena.robot.model import load_robot_model
from tests.conftest import REPOSITORY, RunningServer, need

Start = Callable[..., Awaitable[RunningServer]]
#: Bounds only a broken command reaches (torch and LeRobot take seconds to import, and the
#: policy's worker is started twice).
RUN = 900.0
LOAD = 120.0


async def test_one_small_round_corrects_exports_and_retrains(
    start_server: Start, tmp_path: Path
) -> None:
    lerobot_dataset = need("lerobot.datasets.lerobot_dataset", "lerobot")
    need("gymnasium", "gym")
    need("mujoco", "physics")
    from arena.gym.dagger import ROLLOUT_SEED, expert_labels, target_key, target_of
    from arena.gym.task import Reach

    out = tmp_path / "dagger"
    with trio.fail_after(RUN):
        done = await trio.run_process(
            [
                sys.executable,
                "-m",
                "arena",
                "learn",
                "reach",
                "-o",
                str(out),
                "--robot-type",
                "so-101",
                "--dagger",
                "1",
                "--demos",
                "2",
                "--rollouts",
                "2",
                "--steps",
                "10",
                "--targets",
                "1",
            ],
            capture_stdout=True,
            capture_stderr=True,
            check=False,
            env={**os.environ, "PYTHONPATH": str(REPOSITORY)},
        )
    said = done.stdout.decode()
    assert done.returncode == 0, said + done.stderr.decode()
    report = json.loads((out / "report.json").read_text())
    first, second = report["rounds"]
    assert "round 0 " in said and "round 1 " in said
    assert f"policy saved in {out / 'round-1' / 'policy'}" in said

    # The corrector intervened, through the robot's intervention, and commanded.
    assert first["rollouts"] == 2 and first["interventions"] >= 1
    (recording,) = sorted((out / "round-0" / "recordings").glob("*.mcap"))
    messages = read_recording(recording).messages
    changes = [m.data for m in messages if m.kind == "intervention"]
    started = [c for c in changes if c["change"] == "started"]
    assert len(started) == first["interventions"]
    assert all(c["master"] == "corrector" for c in changes)
    assert sum(c["change"] == "ended" for c in changes) == len(started)
    accepted = [m for m in messages if m.kind == "command" and m.data["accepted"]]
    assert any(m.data["source"] == "corrector" for m in accepted)
    starts = [m for m in messages if m.kind == "episode" and m.data["change"] == "start"]
    assert len(starts) == 2

    # The deployments, exported by Arena: the corrector's frames flagged, each frame with
    # its episode's target.
    root = out / "round-0" / "rollouts"
    arena_info = json.loads((root / "meta" / "arena.json").read_text())
    assert arena_info["corrections"] and all(m == "corrector" for _, m in arena_info["corrections"])
    repo_id = json.loads((root / "meta" / "info.json").read_text()).get("repo_id")
    dataset = lerobot_dataset.LeRobotDataset(repo_id or "arena/reach-rollouts-0", root=root)
    feature = dataset.meta.features["intervention"]
    assert feature["dtype"] == "bool" and tuple(feature["shape"]) == (1,)
    assert dataset.num_episodes == 2
    table = dataset.hf_dataset.with_format("numpy")
    columns = {name: np.asarray(table[name]) for name in table.column_names}
    flags = columns["intervention"].reshape(-1).astype(bool)
    assert len(flags) == first["rollout_frames"] and flags.sum() == first["correction_frames"] > 0
    task = Reach(load_robot_model("so-101"))
    targets = [target_of(task, ROLLOUT_SEED + k) for k in range(2)]  # the rollouts' own
    for state in columns["observation.environment_state"]:
        assert any(np.allclose(state, target, atol=1e-6) for target in targets)

    # DAgger's labels: every frame's action relabelled by the expert following the episode.
    # Where the corrector commanded, that is its command (the same function of state);
    # where the policy drove, what the expert would have done there instead.
    # The corrector held its sag compensation fixed, learned in the twin for each target
    # (the demonstrations' and the deployments'), as report.json keeps it.
    compensation = {tuple(target): bias for target, bias in report["compensation"]}
    assert len(compensation) == 4 and all(len(bias) == 4 for bias in compensation.values())
    assert all(target_key(target) in compensation for target in targets)

    def bias_of(target: object) -> list[float]:
        return compensation[target_key(target)]  # type: ignore[arg-type]

    labels = expert_labels(task.model, bias_of)(columns)
    assert np.allclose(labels[flags], columns["action"][flags], atol=1e-3)
    assert np.abs(labels[~flags] - columns["action"][~flags]).max() > 1.0

    # The data grew by the relabelled deployments, and round 1 trained on it all.
    assert second["frames"] == first["frames"] + first["rollout_frames"]
    assert second["rollouts"] == 0 and 0.0 <= second["success"] <= 1.0
    assert set(first["cpu_seconds"]) == {"collect", "train", "evaluate", "rollouts"}

    # The retrained policy is what a server's policy master loads, target and all.
    server = await start_server()
    async with httpx.AsyncClient(base_url=server.url, timeout=LOAD) as http:
        made = await http.post("/api/robots", json={"id": "arm", "robot_type": "so-101"})
        assert made.status_code == 201, made.text
        slave = await http.post("/api/robots/arm/slaves", json={"type": "mock-slave"})
        assert slave.status_code == 201, slave.text
        body = {
            "type": "policy",
            "path": second["policy_dir"],
            "environment_state": [0.3, 0.0, 0.2],
        }
        attached = await http.post("/api/robots/arm/master", json=body)
        assert attached.status_code == 201, attached.text
        assert attached.json()["id"].startswith("policy:act:")
        await http.delete("/api/robots/arm/master")


def test_the_policy_strays_after_half_a_second_without_progress() -> None:
    need("gymnasium", "gym")
    from arena.gym.deploy import Stray

    stray = Stray(30.0)  # 15 steps
    # Coming closer by 3 mm a step is progress, however far it still is.
    assert not any(stray.update(0.30 - 0.003 * k) for k in range(40))
    # Arriving 5 cm away (progress) and standing still there: 15 steps (half a second)
    # later it strays, not a step earlier.
    stuck = [stray.update(0.05) for _ in range(17)]
    assert stuck.index(True) == 15
    # Holding within the success distance is what it should do: no stray.
    stray.restart()
    assert not any(stray.update(0.015) for _ in range(60))
    # Drifting away strays too.
    stray.restart()
    assert any(stray.update(0.03 + 0.001 * k) for k in range(16))


def test_a_following_expert_stays_on_a_leash_from_the_arm() -> None:
    """The corrector's commands are eased in at the joining speed: its plan must not run
    away from an arm that moves slowly, or its actions label states they do not fit."""
    need("gymnasium", "gym")
    from arena.gym.task import ARM_JOINTS, EXPERT_LEASH, EXPERT_STEP, Expert, Reach

    task = Reach(load_robot_model("so-101"))
    rng = np.random.default_rng(3)
    target = task.draw_target(rng)
    arm = np.zeros(6)
    free, leashed = Expert(task, target, arm), Expert(task, target, arm, follow=True)
    for _ in range(20):  # the arm does not move at all
        ahead = np.abs(free.act(arm)[:ARM_JOINTS]).max()
        near = np.abs(leashed.act(arm)[:ARM_JOINTS]).max()
    assert near <= EXPERT_LEASH + EXPERT_STEP + 1e-9 < ahead


def test_dagger_labels_are_what_the_following_expert_does_from_each_frame() -> None:
    """A policy that never moved the arm: its frames are relabelled with the expert's actions
    from where the arm is (toward the target, on the leash from the arm), not its own; each
    episode's expert starts afresh."""
    need("gymnasium", "gym")
    from arena.gym.dagger import expert_labels
    from arena.gym.task import ARM_JOINTS, EXPERT_LEASH, EXPERT_STEP, Reach
    from arena.recording.dataset import ENVIRONMENT, to_dataset

    model = load_robot_model("so-101")
    task = Reach(model)
    target = np.asarray(task.draw_target(np.random.default_rng(5)))
    rest = np.array([to_dataset(joint, 0.0) for joint in model.joints], dtype=np.float32)
    frames = 12
    columns = {
        "observation.state": np.tile(rest, (2 * frames, 1)),
        ENVIRONMENT: np.tile(target, (2 * frames, 1)),
        "episode_index": np.repeat([0, 1], frames),
        "action": np.tile(rest, (2 * frames, 1)),  # what the policy did: nothing
    }
    labels = expert_labels(model)(columns)
    assert labels.shape == columns["action"].shape
    arm = labels[:, :ARM_JOINTS] - rest[:ARM_JOINTS]
    goal = task.solve(target, [0.0] * len(model.joints))[:ARM_JOINTS]
    # Toward the target's joints, every joint, and within the leash of the arm that stayed.
    moving = np.abs(goal) > 1.0
    assert np.all(np.sign(arm[:, moving]) == np.sign(goal[moving]))
    assert np.abs(arm).max() <= EXPERT_LEASH + EXPERT_STEP + 1e-4
    assert np.abs(arm[1]).max() > np.abs(arm[0]).max()  # its plan walks on, one step a frame
    # The wrist's roll and the gripper stay where the arm has them (in the dataset's units).
    assert np.allclose(labels[:, ARM_JOINTS:], rest[ARM_JOINTS:], atol=1e-4)
    # The second episode's expert starts afresh: the same states, the same labels.
    assert np.allclose(labels[:frames], labels[frames:])


def test_a_label_does_not_depend_on_how_long_the_arm_has_lingered() -> None:
    """The expert's integral term wound up on a policy's frames: an arm that stayed 3 cm off
    the target got a label further off with every frame (the same state, ever other
    labels), and the policy learned to overshoot. With its sag compensation held fixed, the
    label of a state is the same on the first frame there and the hundredth."""
    need("gymnasium", "gym")
    from arena.gym.dagger import expert_labels
    from arena.gym.task import ARM_JOINTS, Reach
    from arena.recording.dataset import ENVIRONMENT, to_dataset

    model = load_robot_model("so-101")
    task = Reach(model)
    target = np.asarray(task.draw_target(np.random.default_rng(7)))
    rest = [0.0] * len(model.joints)
    # A pose whose tip is 3 cm below the target: where a policy that undershoots stops.
    short = task.solve(np.asarray(target) - [0.0, 0.0, 0.03], rest)
    assert 0.025 < task.distance(short, target) < 0.035
    state = np.array([to_dataset(j, float(v)) for j, v in zip(model.joints, short, strict=True)])
    frames = 100
    columns = {
        "observation.state": np.tile(state, (frames, 1)).astype(np.float32),
        ENVIRONMENT: np.tile(target, (frames, 1)),
        "episode_index": np.zeros(frames, dtype=np.int64),
        "action": np.tile(state, (frames, 1)).astype(np.float32),
    }
    bias = [0.2, -3.0, -2.0, -1.0]
    labels = expert_labels(model, lambda _: bias)(columns)[:, :ARM_JOINTS]
    # Once the plan has walked to the goal (a few frames), every label is the goal plus the
    # compensation, frame after frame.
    goal = task.solve(target, short)[:ARM_JOINTS] + bias
    wanted = [to_dataset(joint, float(v)) for joint, v in zip(model.joints, goal, strict=False)]
    assert np.allclose(labels[20:], labels[20], atol=1e-4)
    assert np.allclose(labels[20], wanted, atol=0.05)


def test_the_compensation_learned_in_the_twin_takes_the_tip_onto_the_target() -> None:
    """The expert's bias settled in the twin (its integral term run from rest), held fixed
    from the first frame: the tip reaches the target and stays within a few millimetres,
    where without it the arm's sag leaves the tip centimetres off."""
    need("gymnasium", "gym")
    need("mujoco", "physics")
    from arena.gym.dagger import Compensation, target_of
    from arena.gym.task import ARM_JOINTS, Expert, Reach
    from arena.gym.worlds import TwinWorld, command_of

    world = TwinWorld("so-101", 30.0)
    task = Reach(world.model)
    target = target_of(task, 11)
    compensation = Compensation()

    async def run(bias: list[float]) -> float:
        measured = await world.reset_now(target)
        expert = Expert(task, target, measured, follow=True, bias=bias)
        for _ in range(60):
            action = expert.act(world.measured())
            await world.command(command_of(world.model, action.tolist()))
            await world.advance(world.period)
        return task.distance(world.measured(), target)

    try:
        bias = world.loop.call(compensation.learn, world, target)
        assert compensation(target) == bias and np.abs(bias).max() > 0.5
        compensated = world.loop.call(run, bias)
        sagging = world.loop.call(run, [0.0] * ARM_JOINTS)
    finally:
        world.close()
    assert compensated < 0.005 < sagging
