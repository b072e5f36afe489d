"""Time Arena's planned paths on this machine: p50 and p99 per robot type.

    python tools/plan_timing.py [--count 40] [--budget 1.0]
    python tools/plan_timing.py --loop [--no-yield]   # the event loop while plans run

Two cases (specs/cartesian.md, "Planned paths"), each with a pillar (a keep-out box) standing
where the hand reaches out low in front of the arm: the arm turning its pan between two sides
of the pillar (the straight way runs into it: a search is needed; a scene whose start or goal
would touch the pillar is drawn again), and between two random poses that clear the pillar
(often the straight way is free: no search). The time is the whole of `planning.plan`:
checks, search, simplifier and timing.

`--loop`: how late a 1 ms `trio.sleep` wakes on the event loop while a thread plans around
the pillar again and again (the planned move's setting; the garbage collector tuned as
`arena serve` tunes it); `--no-yield` without the plan's pauses (`planning.YIELD_EVERY`).
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import math
import random
import statistics
import time

import trio

from arena.robot import collision, planning
from arena.robot.cartesian import hand_for
from arena.robot.model import RobotModel, load_robot_model
from arena.robot.workspace import Box, Workspace
from arena.server.run import tune_garbage_collector


def pillar_scene(
    rng: random.Random, model: RobotModel
) -> tuple[dict[str, float], dict[str, float], Workspace]:
    """The hand out 18-26 cm and 5-12 cm up, the pan turned 35-60 degrees each way, and a
    6 cm square pillar where the hand passes at pan zero."""
    hand = hand_for(model)
    assert hand is not None
    zero = {j.name: 0.0 for j in model.joints}
    out = hand.pose(zero)
    assert out is not None
    across = math.hypot(out.position[0], out.position[1])
    reach, height = rng.uniform(0.18, 0.26), rng.uniform(0.05, 0.12)
    target = (out.position[0] / across * reach, out.position[1] / across * reach, height)
    solved = hand.solve(target, None, zero)
    pose = {**zero, **solved.joints}
    there = hand.pose(pose)
    assert there is not None
    x, y, z = there.position
    box = Box("pillar", (x - 0.03, y - 0.03, 0.0), (x + 0.03, y + 0.03, z + 0.04))
    workspace = Workspace(floor=model.workspace.floor, keep_out=(box,), margin=0.005)
    pan, turn = hand.joint_names[0], rng.uniform(35, 60)
    return {**pose, pan: pose[pan] - turn}, {**pose, pan: pose[pan] + turn}, workspace


def random_pose(
    rng: random.Random, model: RobotModel, guard: collision.CollisionModel, workspace: Workspace
) -> dict[str, float]:
    """Joint values from the middle 70 % of each range that the guard finds clear."""
    while True:
        values = {
            j.name: (j.lower + j.upper) / 2 + rng.uniform(-0.7, 0.7) * (j.upper - j.lower) / 2
            for j in model.joints
        }
        pose = {j.urdf_name: j.to_urdf(values[j.name]) for j in model.joints}
        if guard.hit(pose, workspace) is None:
            return values


def loop_lateness(count: int, budget: float) -> None:
    """Print how late the event loop's 1 ms sleeps wake while `count` plans run in a thread."""
    model = load_robot_model("so-arm100")
    guard = collision.for_model(model)
    assert guard is not None
    rng = random.Random(58)
    pillar_scene(rng, model)  # built once before: the hand's chain, OMPL imported
    planning.ompl_modules()
    tune_garbage_collector()  # as `arena serve` does once it is up
    planning.plan(
        model,
        guard,
        Workspace(),
        {j.name: 0.0 for j in model.joints},
        {j.name: 1.0 for j in model.joints},
    )

    def plans() -> None:
        for _ in range(count):
            start, goal, workspace = pillar_scene(rng, model)
            with contextlib.suppress(planning.NoPath):
                planning.plan(model, guard, workspace, start, goal, budget=budget)

    async def measure() -> list[float]:
        late: list[float] = []
        done = trio.Event()

        async def tick() -> None:
            while not done.is_set():
                began = time.perf_counter()
                await trio.sleep(0.001)
                late.append(time.perf_counter() - began - 0.001)

        async with trio.open_nursery() as nursery:
            nursery.start_soon(tick)
            await trio.to_thread.run_sync(functools.partial(plans))
            done.set()
        return sorted(late)

    late = trio.run(measure)
    p99 = late[min(len(late) - 1, math.ceil(0.99 * len(late)) - 1)]
    print(
        f"1 ms sleeps: {len(late)}, late by p50 {statistics.median(late) * 1000:.2f} ms, "
        f"p99 {p99 * 1000:.2f} ms, max {late[-1] * 1000:.2f} ms"
    )


def main() -> None:
    """Print the table (or, with --loop, the event loop's lateness)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--count", type=int, default=40)
    parser.add_argument("--budget", type=float, default=planning.DEFAULT_BUDGET)
    parser.add_argument("--loop", action="store_true")
    parser.add_argument("--no-yield", action="store_true")
    args = parser.parse_args()
    if args.no_yield:
        planning.YIELD_EVERY = math.inf
    if args.loop:
        loop_lateness(args.count, args.budget)
        return
    print("| robot type | case | p50 ms | p99 ms | found | straight | corners | move s |")
    print("|---|---|---|---|---|---|---|---|")
    for robot_type in ("so-arm100", "so-101", "koch"):
        model = load_robot_model(robot_type)
        guard = collision.for_model(model)
        assert guard is not None
        rng = random.Random(58)
        for case in ("around the pillar", "random poses"):
            times: list[float] = []
            found = straight = 0
            corners: list[int] = []
            durations: list[float] = []
            for _ in range(args.count):
                while True:  # a scene whose start and goal clear the pillar
                    start, goal, workspace = pillar_scene(rng, model)
                    if all(
                        guard.hit(
                            {j.urdf_name: j.to_urdf(p[j.name]) for j in model.joints}, workspace
                        )
                        is None
                        for p in (start, goal)
                    ):
                        break
                if case == "random poses":
                    start = random_pose(rng, model, guard, workspace)
                    goal = random_pose(rng, model, guard, workspace)
                began = time.perf_counter()
                try:
                    path = planning.plan(model, guard, workspace, start, goal, budget=args.budget)
                except planning.NoPath:
                    times.append(time.perf_counter() - began)
                    continue
                times.append(time.perf_counter() - began)
                found += 1
                straight += path.straight
                corners.append(len(path.waypoints))
                durations.append(path.duration)
            times.sort()
            p50 = statistics.median(times) * 1000
            p99 = times[min(len(times) - 1, math.ceil(0.99 * len(times)) - 1)] * 1000
            print(
                f"| {robot_type} | {case} | {p50:.0f} | {p99:.0f} | {found}/{args.count} | "
                f"{straight} | {statistics.mean(corners or [0]):.1f} | "
                f"{statistics.mean(durations or [0]):.2f} |"
            )


if __name__ == "__main__":
    main()
