"""Stable-Baselines3's PPO on Arena's reach environment as it is, in the physics twin:

    python examples/ppo_reach.py [--steps 4096] [--save ppo_reach.zip]

The environment is not changed for the library (no wrapper of Arena's own): observations are
the dict of `agent_pos` and `environment_state`, actions the six joint targets in
`observation.state`'s units. A few thousand steps show that it trains; reaching well takes far
more (the expert and `arena learn` are the quick way; specs/learning.md).
"""

from __future__ import annotations

import argparse
import time


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--steps", type=int, default=4096, help="environment steps (4096)")
    parser.add_argument("--save", default="", help="where to save the model (a .zip)")
    args = parser.parse_args()

    import gymnasium
    import torch
    from stable_baselines3 import PPO

    import arena.gym

    torch.set_num_threads(1)  # a small model on a small machine: threads only fight
    env = gymnasium.make(arena.gym.ENV_ID)
    model = PPO("MultiInputPolicy", env, n_steps=512, batch_size=64, seed=0, verbose=0)
    started = time.perf_counter()
    model.learn(total_timesteps=args.steps)
    took = time.perf_counter() - started
    returns = [float(episode["r"]) for episode in model.ep_info_buffer]
    mean = sum(returns) / len(returns) if returns else float("nan")
    print(f"PPO: {model.num_timesteps} steps in {took:.0f} s; mean episode return {mean:.2f}")
    if args.save:
        model.save(args.save)
        print(f"saved {args.save}")
    env.close()


if __name__ == "__main__":
    main()
