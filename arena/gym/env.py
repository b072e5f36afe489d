"""`ArenaEnv`: the reach task as a Gymnasium environment, its robot driven through Arena.

Observations are what LeRobot's environment wrappers take: `agent_pos` (the measured joints in
the units and order of `observation.state`, specs/lerobot.md), `environment_state` (the
target, metres in the base's frame) and, with `cameras`, `pixels` (an image a camera, by name:
the twin's MuJoCo scene rendered). Actions are the six joint targets in the same units.
Reward is minus the tip's distance to the target (metres). An episode is `terminated` on
success (the tip within 2 cm for 0.5 s) or when Arena refuses a command or the robot is
e-stopped (the reason in `info["safety"]`); `truncated` at its time limit.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, SupportsFloat, cast

import gymnasium
import numpy as np
import numpy.typing as npt
from gymnasium import spaces

from arena.drivers.physics import View
from arena.gym.task import SUCCESS_DISTANCE, Reach, Success
from arena.gym.worlds import ServerWorld, TwinWorld, World
from arena.recording.dataset import from_dataset, to_dataset

#: The reach task's episode length (seconds) unless the caller says otherwise.
DEFAULT_EPISODE_SECONDS = 6.0
#: How far (in the joints' units) a measured value may lie outside its limits and still be in
#: the observation space: a loaded arm sags past its targets.
OBSERVATION_MARGIN = 10.0
#: Targets lie within this distance (metres) of the base in every axis.
REACH = 1.0

Observation = dict[str, npt.NDArray[np.float32]]
Action = npt.NDArray[np.float32]


class ArenaEnv(gymnasium.Env[Observation, Action]):
    """The reach task on an Arena robot.

    `ArenaEnv()` runs a private Arena with the physics twin, stepped (not paced) and the same
    every time for the same seed; `ArenaEnv(url="http://HOST:PORT", robot="ID")` drives a
    robot of a running server in real time, paced to `fps`. `max_seconds` is the episode's
    time limit. Against a server, `observation_wait` is how long a step waits at most, after
    its tick, for the joint states its command caused (default one period).
    """

    metadata = {"render_modes": [], "render_fps": 30}  # noqa: RUF012 (Gymnasium's own shape)

    def __init__(
        self,
        url: str | None = None,
        robot: str | None = None,
        *,
        robot_type: str = "so-arm100",
        fps: float = 30.0,
        max_seconds: float = DEFAULT_EPISODE_SECONDS,
        api_key: str | None = None,
        takeover: bool = False,
        cameras: Sequence[str] = (),
        image_size: tuple[int, int] = (96, 96),
        world: World | None = None,
        observation_wait: float | None = None,
    ) -> None:
        if world is None:
            if url is not None:
                if robot is None:
                    raise ValueError("a server's robot needs its id: ArenaEnv(url=..., robot=...)")
                if cameras:
                    raise ValueError("`pixels` against a server are not there yet: no cameras")
                world = ServerWorld(
                    url,
                    robot,
                    fps,
                    api_key=api_key,
                    takeover=takeover,
                    observation_wait=observation_wait,
                )
            else:
                world = TwinWorld(robot_type, fps, cameras=dict.fromkeys(cameras, View()))
        self.cameras = tuple(cameras)
        self.image_size = image_size
        self.world = world
        self.model = world.model
        self.task = Reach(self.model)
        self.fps = world.fps
        self.max_steps = max(1, round(max_seconds * self.fps))
        self.metadata = {"render_modes": [], "render_fps": self.fps}
        joints = self.model.joints
        low = np.array([to_dataset(j, j.lower) for j in joints], dtype=np.float32)
        high = np.array([to_dataset(j, j.upper) for j in joints], dtype=np.float32)
        self.action_space = spaces.Box(low, high, dtype=np.float32)
        observations = spaces.Dict(
            {
                "agent_pos": spaces.Box(
                    low - OBSERVATION_MARGIN, high + OBSERVATION_MARGIN, dtype=np.float32
                ),
                "environment_state": spaces.Box(-REACH, REACH, (3,), dtype=np.float32),
            }
        )
        if self.cameras:
            shape = (*image_size, 3)
            observations["pixels"] = spaces.Dict(
                {name: spaces.Box(0, 255, shape, dtype=np.uint8) for name in self.cameras}
            )
        self.observation_space = cast("spaces.Space[Observation]", observations)
        self.target: tuple[float, float, float] = (0.0, 0.0, 0.0)
        self._measured: tuple[float, ...] = ()
        self._steps = 0
        self._success = Success(self.fps)
        self._over = True

    # -- units ---------------------------------------------------------------------------------

    def to_action(self, joints: Sequence[float] | npt.NDArray[Any]) -> Action:
        """Arena's joint values (wire units, servo order) as an action of this environment."""
        values = [to_dataset(j, v) for j, v in zip(self.model.joints, joints, strict=True)]
        return np.asarray(values, dtype=np.float32)

    def from_action(self, action: Sequence[float] | npt.NDArray[Any]) -> tuple[float, ...]:
        """An action of this environment as Arena's joint values."""
        return tuple(
            from_dataset(j, float(v)) for j, v in zip(self.model.joints, action, strict=True)
        )

    def _observation(self) -> Observation:
        observation: dict[str, Any] = {
            "agent_pos": self.to_action(self._measured),
            "environment_state": np.asarray(self.target, dtype=np.float32),
        }
        if self.cameras:
            observation["pixels"] = self.world.images(self.image_size)
        return observation

    def _info(self) -> dict[str, Any]:
        return {
            "distance": self.task.distance(self._measured, self.target),
            "is_success": self._success.held >= self._success.needed,
            "measured": self._measured,
        }

    # -- Gymnasium -----------------------------------------------------------------------------

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[Observation, dict[str, Any]]:
        """Bring the arm to rest through Arena and draw a new target (`options["target"]`
        sets one instead)."""
        super().reset(seed=seed)
        chosen = (options or {}).get("target")
        if chosen is not None:
            x, y, z = (float(v) for v in chosen)
        else:
            x, y, z = self.task.draw_target(self.np_random)
        self.target = (x, y, z)
        self._measured = self.world.reset(self.target)
        self._steps = 0
        self._success = Success(self.fps)
        self._over = False
        return self._observation(), self._info()

    def step(self, action: Action) -> tuple[Observation, SupportsFloat, bool, bool, dict[str, Any]]:
        """Send one command (the action, clipped to the joints' limits by Arena as any
        command is) and return what followed one period later."""
        if self._over:
            raise RuntimeError("the episode is over: call reset() first")
        targets = self.from_action(np.asarray(action, dtype=np.float64).reshape(-1))
        self._measured, safety = self.world.step(targets)
        self._steps += 1
        distance = self.task.distance(self._measured, self.target)
        success = self._success.update(distance)
        info = self._info()
        if safety is not None:
            info["safety"] = safety
        terminated = success or safety is not None
        truncated = not terminated and self._steps >= self.max_steps
        self._over = terminated or truncated
        return self._observation(), -distance, terminated, truncated, info

    def close(self) -> None:
        """Let the robot go (a private Arena stops)."""
        self.world.close()
        super().close()


__all__ = ["SUCCESS_DISTANCE", "ArenaEnv"]
