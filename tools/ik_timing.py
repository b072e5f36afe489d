"""Time Arena's inverse kinematics on this machine: p50 and p99 per robot type.

    python tools/ik_timing.py [--count 300]

Three cases (specs/cartesian.md): a step of a few centimetres from where the hand is (what an
agent's next pose or a teleoperation tick asks), a pose anywhere useful from an unrelated start,
and a point out of reach (every start is tried).
"""

from __future__ import annotations

import argparse
import random
import statistics
import time

from arena.robot.cartesian import Hand, hand_for
from arena.robot.model import RobotModel, load_robot_model


def useful(rng: random.Random, model: RobotModel, hand: Hand, spread: float = 0.7) -> dict:
    """Joint values from the middle of each range with the tool point above the table."""
    while True:
        values = {
            j.name: (j.lower + j.upper) / 2 + rng.uniform(-spread, spread) * (j.upper - j.lower) / 2
            for j in model.joints
        }
        pose = hand.pose(values)
        assert pose is not None
        if pose.position[2] > 0.03:
            return values


def main() -> None:
    """Print the table."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--count", type=int, default=300)
    count = parser.parse_args().count
    print("| robot type | case | p50 ms | p99 ms | reached |")
    print("|---|---|---|---|---|")
    for robot_type in ("so-arm100", "so-101", "koch"):
        model = load_robot_model(robot_type)
        hand = hand_for(model)
        assert hand is not None
        rng = random.Random(7)

        cases = {"a step of 2 cm": [], "anywhere": [], "out of reach": []}
        reached: dict[str, int] = dict.fromkeys(cases, 0)
        for _ in range(count):
            start = useful(rng, model, hand)
            here = hand.pose(start)
            assert here is not None
            step = [rng.uniform(-1, 1) for _ in range(3)]
            norm = sum(c * c for c in step) ** 0.5 or 1.0
            near = tuple(p + 0.02 * c / norm for p, c in zip(here.position, step, strict=True))
            goal = hand.pose(useful(rng, model, hand))
            assert goal is not None
            for case, target in (
                ("a step of 2 cm", near),
                ("anywhere", goal.position),
                ("out of reach", (1.5, rng.uniform(-1, 1), 0.3)),
            ):
                began = time.perf_counter()
                solution = hand.solve(target, None, start)  # type: ignore[arg-type]
                cases[case].append(time.perf_counter() - began)
                reached[case] += solution.reached
        for case, times in cases.items():
            cuts = statistics.quantiles(times, n=100)
            print(
                f"| {robot_type} | {case} | {cuts[49] * 1000:.2f} | {cuts[98] * 1000:.2f} "
                f"| {reached[case]}/{count} |"
            )


if __name__ == "__main__":
    main()
