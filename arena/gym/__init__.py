"""Gymnasium environments on Arena robots (the `gym` extra): `ArenaEnv`, the reach task,
registered as `arena/Reach-v0` (`gymnasium.make("arena/Reach-v0")`; with `url=` and `robot=` it
drives a robot of a running server). See specs/learning.md."""

from __future__ import annotations

import gymnasium

from arena.gym.env import ArenaEnv

ENV_ID = "arena/Reach-v0"

if ENV_ID not in gymnasium.registry:
    gymnasium.register(id=ENV_ID, entry_point="arena.gym.env:ArenaEnv")

__all__ = ["ENV_ID", "ArenaEnv"]
