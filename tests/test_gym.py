"""The Gymnasium environment (`arena.gym`): Gymnasium's own checks in both ways of running it,
the same seed giving the same run in the twin, the scripted expert solving the reach task, and
Arena's safety ending an episode (a command into the table, an e-stop over REST)."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import trio

from arena.robot.model import BUILTIN_TYPES_DIR
from tests.conftest import REPOSITORY, RunningServer, missing, need

gymnasium = need("gymnasium", "gym")
need("mujoco", "physics")

from gymnasium.utils.env_checker import check_env  # noqa: E402

from arena.gym import ENV_ID, ArenaEnv  # noqa: E402
from arena.gym.task import Expert  # noqa: E402

Start = Callable[..., Awaitable[RunningServer]]


@pytest.fixture(scope="module")
def twin() -> Any:
    """One self-contained environment for the module (building the twin takes a second)."""
    env = gymnasium.make(ENV_ID)
    yield env.unwrapped
    env.close()


def run(env: ArenaEnv, seed: int, steps: int) -> list[np.ndarray]:
    """Observations of an episode with actions drawn from `seed`."""
    observation, _ = env.reset(seed=seed)
    rng = np.random.default_rng(seed)
    seen = [np.concatenate([observation["agent_pos"], observation["environment_state"]])]
    action = observation["agent_pos"]
    for _ in range(steps):
        action = action + rng.uniform(-2.0, 2.0, 6).astype(np.float32)
        action = np.clip(action, env.action_space.low, env.action_space.high)
        observation, _, terminated, truncated, _ = env.step(action)
        seen.append(np.concatenate([observation["agent_pos"], observation["environment_state"]]))
        if terminated or truncated:
            break
    return seen


def test_check_env_passes_in_the_twin(twin: ArenaEnv) -> None:
    check_env(twin, skip_render_check=True)


def test_the_same_seed_gives_the_same_observations(twin: ArenaEnv) -> None:
    first = run(twin, seed=7, steps=40)
    other = run(twin, seed=8, steps=40)
    again = run(twin, seed=7, steps=40)
    assert len(first) == 41
    assert all(np.array_equal(a, b) for a, b in zip(first, again, strict=True))
    assert not np.array_equal(first[0][6:], other[0][6:])  # another target
    assert not np.array_equal(first[-1][:6], other[-1][:6])  # other actions, another way


def test_the_expert_reaches_its_targets(twin: ArenaEnv) -> None:
    for seed in range(5):
        observation, info = twin.reset(seed=seed)
        simulation = twin.world.slave.simulation  # the target is shown in the MuJoCo scene
        assert np.allclose(simulation.target(), observation["environment_state"], atol=1e-6)
        start = info["distance"]
        expert = Expert(twin.task, twin.target, info["measured"])
        for _ in range(twin.max_steps):
            action = twin.to_action(expert.act(info["measured"]))
            observation, reward, terminated, truncated, info = twin.step(action)
            if terminated or truncated:
                break
        assert terminated and not truncated, f"seed {seed}: {info}"
        assert info["is_success"] and "safety" not in info
        assert info["distance"] <= 0.02 < start
        assert float(reward) == pytest.approx(-info["distance"])


def test_the_expert_reaches_its_targets_on_the_so_101() -> None:
    """The reach task on the arm users own: its tip is the far end of the fixed jaw on the
    so-101's own link, and the expert reaches targets drawn for it in its twin."""
    env = ArenaEnv(robot_type="so-101")
    try:
        assert env.task.tip_link == "gripper_link"  # the gripper joint's parent in its URDF
        for seed in range(3):
            _, info = env.reset(seed=seed)
            start = info["distance"]
            expert = Expert(env.task, env.target, info["measured"])
            for _ in range(env.max_steps):
                action = env.to_action(expert.act(info["measured"]))
                _, _, terminated, truncated, info = env.step(action)
                if terminated or truncated:
                    break
            assert terminated and info["is_success"] and "safety" not in info, f"seed {seed}"
            assert info["distance"] <= 0.02 < start
    finally:
        env.close()


def test_the_gripper_driven_into_the_table_ends_the_episode(twin: ArenaEnv) -> None:
    observation, info = twin.reset(seed=1)
    down = observation["agent_pos"].copy()
    for _ in range(twin.max_steps):
        down[1] += 3.0  # the shoulder lifts the arm forward and down, onto the table
        down[2] += 3.0
        observation, _, terminated, truncated, info = twin.step(down)
        if terminated or truncated:
            break
    assert terminated and not info["is_success"]
    assert info["safety"]["code"] == "COLLISION", info
    assert "table" in info["safety"]["message"] or "floor" in info["safety"]["message"]
    with pytest.raises(RuntimeError, match="reset"):
        twin.step(down)
    observation, info = twin.reset(seed=1)  # the next episode starts clean
    assert "safety" not in info and np.allclose(observation["agent_pos"][:5], 0.0)


# -- against a server -------------------------------------------------------------------------


@pytest.fixture
def fast_type(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> str:
    """The so-arm100 with joints that move as fast as asked: a mock slave then reports every
    target of a step at once, so a run against a server is as repeatable as Gymnasium's checks
    ask (the real type's velocity limit spreads a large step over the next ticks)."""
    folder = tmp_path / "types" / "fast-arm"
    shutil.copytree(BUILTIN_TYPES_DIR / "so-arm100", folder)
    urdf = folder / "so-arm100.urdf"
    fast = urdf.read_text(encoding="utf-8").replace('velocity="4.71239"', 'velocity="100000"')
    assert fast.count('velocity="100000"') == 6
    urdf.write_text(fast, encoding="utf-8")
    monkeypatch.setenv("ARENA_ROBOT_TYPES", str(tmp_path / "types"))
    return "fast-arm"


async def robot_with_mock_slave(server: RunningServer, robot_type: str) -> None:
    async with server.client() as http:
        made = await http.post("/api/robots", json={"id": "arm", "robot_type": robot_type})
        assert made.status_code == 201, made.text
        slave = await http.post("/api/robots/arm/slaves", json={"type": "mock-slave"})
        assert slave.status_code == 201, slave.text


async def test_check_env_passes_against_a_server(start_server: Start, fast_type: str) -> None:
    # Joint states at most 2 ms apart (20 ms by default): each step's observation is the
    # mock slave's report of that step's command, whatever came just before it.
    server = await start_server(joint_states_interval=0.002)
    await robot_with_mock_slave(server, fast_type)

    def check() -> None:
        # Each step waits for the joint states its command caused however late they come (a
        # real-time loop waits one period at most): a loaded machine slows the check, never
        # fails it.
        env = gymnasium.make(ENV_ID, url=server.url, robot="arm", observation_wait=60.0)
        try:
            # (Its close check makes a second environment while this one holds the robot,
            # which Arena refuses: MASTER_ACTIVE. Closing is checked below.)
            check_env(env.unwrapped, skip_render_check=True, skip_close_check=True)
            observation, _ = env.reset(seed=3)
            assert np.array_equal(observation["agent_pos"][:5], np.zeros(5, np.float32))
        finally:
            env.close()

    await trio.to_thread.run_sync(check)
    async with server.client() as http:  # closed: released, holding, not e-stopped
        robot = (await http.get("/api/robots/arm")).json()
    assert robot["state"] == "idle" and robot["master"] is None, robot


async def test_an_estop_over_rest_ends_an_episode_against_a_server(start_server: Start) -> None:
    server = await start_server()
    await robot_with_mock_slave(server, "so-arm100")
    env = await trio.to_thread.run_sync(lambda: ArenaEnv(url=server.url, robot="arm"))
    try:
        observation, _ = await trio.to_thread.run_sync(lambda: env.reset(seed=0))
        action = observation["agent_pos"]
        for _ in range(3):
            _, _, terminated, _, info = await trio.to_thread.run_sync(env.step, action)
            assert not terminated and "safety" not in info
        async with server.client() as http:
            stopped = await http.post("/api/robots/arm/estop", json={"reason": "hands off"})
            assert stopped.status_code == 200, stopped.text
        _, _, terminated, truncated, info = await trio.to_thread.run_sync(env.step, action)
        assert terminated and not truncated
        assert info["safety"]["code"] == "ESTOPPED", info
        assert "hands off" in info["safety"]["message"]
        with pytest.raises(RuntimeError, match="e-stopped"):
            await trio.to_thread.run_sync(lambda: env.reset(seed=1))
    finally:
        await trio.to_thread.run_sync(env.close)


def test_stable_baselines3_trains_on_the_environment_as_it_is(tmp_path: Path) -> None:
    need("stable_baselines3", "dev")
    saved = tmp_path / "ppo.zip"
    done = subprocess.run(
        [
            sys.executable,
            str(REPOSITORY / "examples" / "ppo_reach.py"),
            "--steps",
            "2048",
            "--save",
            str(saved),
        ],
        capture_output=True,
        text=True,
        timeout=600,
        env={**os.environ, "PYTHONPATH": str(REPOSITORY)},
        check=False,
    )
    assert done.returncode == 0, done.stderr
    assert "PPO: 2048 steps" in done.stdout, done.stdout
    assert saved.is_file()


def red(image: np.ndarray) -> np.ndarray:
    """Where the target's red sphere shows (a mask)."""
    r, g, b = (image[..., k].astype(int) for k in range(3))
    return (r > 120) & (r > 2 * g) & (r > 2 * b)


def test_pixels_show_the_twin_and_its_target() -> None:
    from arena.drivers.physics import ArmSimulation, View
    from arena.robot.model import load_robot_model

    probe = ArmSimulation(load_robot_model("so-arm100"))
    try:
        probe.render(View(), 8, 8)
    except Exception as exc:  # no GL to render with: OSMesa is a system package
        missing(f"MuJoCo cannot render headless ({exc}): apt-get install libosmesa6")
    finally:
        probe.close()
    env = ArenaEnv(cameras=("front",), image_size=(96, 128))
    try:
        first, _ = env.reset(options={"target": (0.15, -0.2, 0.15)})
        assert env.observation_space.contains(first)
        image = first["pixels"]["front"]
        assert image.shape == (96, 128, 3) and image.dtype == np.uint8
        there = red(image)
        assert there.sum() > 5  # the target is in the scene
        moved, _ = env.reset(options={"target": (-0.15, -0.25, 0.1)})
        elsewhere = red(moved["pixels"]["front"])
        assert elsewhere.sum() > 5 and not np.array_equal(there, elsewhere)
        action = moved["agent_pos"].copy()
        action[0] += 20.0  # the arm turns: the picture changes beyond the target
        later = moved
        for _ in range(10):
            later, *_ = env.step(action)
        difference = np.abs(later["pixels"]["front"].astype(int) - moved["pixels"]["front"])
        changed = (difference > 30).any(axis=-1)
        assert (changed & ~elsewhere).sum() > 20
    finally:
        env.close()
