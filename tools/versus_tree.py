"""Two source trees of Arena in one run: the fleet benchmark's server CPU, or `arena bench
teleop`, alternating between them, medians and the ratio (issue 57: the trajectory's cost and
lag against main's, on a machine whose load changes by the minute).

    python tools/versus_tree.py fleet OTHER_TREE [--rounds 3]
    python tools/versus_tree.py core OTHER_TREE [--rounds 3]
    python tools/versus_tree.py teleop OTHER_TREE [--rounds 3]
    python tools/versus_tree.py sweep OTHER_TREE [--rounds 3]
    python tools/versus_tree.py instructions OTHER_TREE

OTHER_TREE is the root of another checkout (`git archive main | tar -x -C DIR`); this file's
tree is the other side. The fleet is `arena bench fleet`'s (100 robots, a master at 50 Hz and
a slave each, 10 s), its server started from each tree in turn; the teleop bench runs in a
process of its own per tree (`teleop_latency`, a teleported leader). `sweep` is `arena bench
teleop`'s human-like sweep (arena/bench/teleop.py: this tree's leader and simulated buses,
each tree's robot in a process of its own; Arena's side only, LeRobot's is the same for
both). `core` is the fleet's robot
work alone, in process and on simulated time: 100 `RobotCore`s with the fleet's commands
(Rotation and Elbow alternating 0.001 degree, 50 Hz each), ticked as the actor ticks them,
10 s; then every joint on a 12-degree sine (a teleoperation stream). Its figure is the
process's own CPU time (`time.process_time`), which a loaded machine leaves honest where the
fleet's server CPU share is only what the machine gave it. `instructions` is `core`'s work
counted in machine instructions under valgrind's callgrind (10 robots: the fleet's commands
for 20 s, the sine for 6 s; less each tree's own start-up, counted with no commands; what
start-up made frozen, as `arena serve` does, so that a full collection's count is the same
in both trees): the same on every run and every machine load, where CPU seconds on a shared
machine are not.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parents[1]


def _fleet_once(tree: Path) -> dict[str, float]:
    code = (
        "import asyncio, json\n"
        "from arena.bench.common import running_server\n"
        "from arena.bench.fleet import fleet\n"
        "async def main():\n"
        "    async with running_server(True) as server:\n"
        "        return await fleet(server, robots=100, rate=50.0, seconds=10.0)\n"
        "print(json.dumps(asyncio.run(main())))\n"
    )
    return _run(tree, code)


#: The actor's next tick after a command (`RobotCore.reschedule`); in a tree without it
#: (every tick of a stream runs), the one planned, or the core's when none is.
_SCHEDULE = """
def schedule(core, tick, now):
    if hasattr(core, "reschedule"):
        return core.reschedule(tick, now)
    return tick if tick is not None else core.next_tick(now)
"""

_CORE = (
    _SCHEDULE
    + """
import dataclasses, json, math, time
from arena.robot.core import RobotCore
from arena.robot.model import load_robot_model
from arena.robot.motion import Command, JointGoal

model = load_robot_model("so-arm100")
policy = dataclasses.replace(model.safety, command_rate=1e9, command_burst=10**9)
names = [j.name for j in model.joints]

def run(goals):
    cores = [RobotCore(model, 0.0, policy) for _ in range(100)]
    ticks = [None] * 100
    targets = 0
    started = time.process_time()
    for step in range(500):  # 10 s at 50 Hz, each robot's command at its own offset
        for n, core in enumerate(cores):
            now = step * 0.02 + n * 0.0002
            due = ticks[n]
            while due is not None and due <= now:
                targets += core.tick(due) is not None
                due = core.next_tick(due)
            command = Command(tuple(JointGoal(k, v) for k, v in goals(step, n).items()))
            targets += core.command(None, command, now)[1].targets is not None
            ticks[n] = schedule(core, due, now)
    return time.process_time() - started, targets

fleet = run(lambda step, n: {"Rotation": (step % 2) * 0.001, "Elbow": -(step % 2) * 0.001})
sine = run(lambda step, n: {k: 12.0 * math.sin(step * 0.04 + n + i) for i, k in enumerate(names)})
print(json.dumps({"core_fleet_cpu_s": fleet[0], "core_fleet_targets": fleet[1],
                  "core_sine_cpu_s": sine[0], "core_sine_targets": sine[1]}))
"""
)


_COUNTED = (
    _SCHEDULE
    + """
import dataclasses, gc, math, sys
from arena.robot.core import RobotCore
from arena.robot.model import load_robot_model
from arena.robot.motion import Command, JointGoal

which, robots, steps = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
model = load_robot_model("so-arm100")
policy = dataclasses.replace(model.safety, command_rate=1e9, command_burst=10**9)
names = [j.name for j in model.joints]
if which == "fleet":
    goals = lambda step, n: {"Rotation": (step % 2) * 0.001, "Elbow": -(step % 2) * 0.001}
else:
    goals = lambda step, n: {k: 12.0 * math.sin(step * 0.04 + n + i) for i, k in enumerate(names)}
cores = [RobotCore(model, 0.0, policy) for _ in range(robots)]
ticks = [None] * robots
gc.collect()
gc.freeze()  # (as `arena serve` does: a full collection's count is the start-up's, not the work's)
for step in range(steps):
    for n, core in enumerate(cores):
        now = step * 0.02 + n * 0.0002
        due = ticks[n]
        while due is not None and due <= now:
            core.tick(due)
            due = core.next_tick(due)
        core.command(None, Command(tuple(JointGoal(k, v) for k, v in goals(step, n).items())), now)
        ticks[n] = schedule(core, due, now)
"""
)
#: Workloads counted (`instructions`): robots and 50 Hz command steps.
_COUNTS = {"fleet": (10, 1000), "sine": (10, 300)}


def _instructions(tree: Path, which: str, robots: int, steps: int) -> int:
    """Machine instructions `_COUNTED` runs in `tree` (valgrind's callgrind)."""
    counter = ["valgrind", "--tool=callgrind", "--callgrind-out-file=/dev/null"]
    out = subprocess.run(
        [*counter, sys.executable, "-c", _COUNTED, which, str(robots), str(steps)],
        env={**os.environ, "PYTHONPATH": str(tree), "PYTHONHASHSEED": "0"},
        cwd=tree,
        capture_output=True,
        text=True,
        check=True,
    )
    return int(out.stderr.split("Collected : ")[1].split()[0])


def _instructions_once(tree: Path) -> dict[str, float]:
    base = _instructions(tree, "fleet", 10, 0)
    return {
        f"core_{which}_instructions_M": (_instructions(tree, which, *count) - base) / 1e6
        for which, count in _COUNTS.items()
    }


def _core_once(tree: Path) -> dict[str, float]:
    return _run(tree, _CORE)


def _sweep_once(tree: Path) -> dict[str, float]:
    # `arena bench teleop`'s sweep (arena/bench/teleop.py): this tree's leader and simulated
    # buses, `tree`'s robot in a process of its own.
    sys.path.insert(0, str(HERE))
    from arena.bench.teleop import arena_sweep, summarise

    return summarise(arena_sweep(tree=tree), "teleop_sweep_arena")


def _teleop_once(tree: Path) -> dict[str, float]:
    code = (
        "import json\n"
        "from arena.bench.hardware import teleop_latency\n"
        "print(json.dumps(teleop_latency(rate=100.0)))\n"
    )
    return _run(tree, code)


def _run(tree: Path, code: str) -> dict[str, float]:
    env = {**os.environ, "PYTHONPATH": str(tree)}
    for _ in range(3):  # (a loaded machine makes a simulated servo miss its first ping)
        out = subprocess.run(
            [sys.executable, "-c", code], env=env, cwd=tree, capture_output=True, text=True
        )
        if out.returncode == 0:
            result: dict[str, float] = json.loads(out.stdout.strip().splitlines()[-1])
            return result
        print(f"(a run on {tree} failed; again)\n{out.stderr[-500:]}", file=sys.stderr)
    raise RuntimeError(f"three runs on {tree} failed")


def main() -> None:
    """Alternate the two trees; print each round, then medians and this tree's ratio."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("bench", choices=("fleet", "core", "teleop", "sweep", "instructions"))
    parser.add_argument("other", type=Path)
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args()
    once = {
        "fleet": _fleet_once,
        "core": _core_once,
        "teleop": _teleop_once,
        "sweep": _sweep_once,
        "instructions": _instructions_once,
    }[args.bench]
    trees = {"other": args.other.resolve(), "this": HERE}
    runs: dict[str, list[dict[str, float]]] = {"other": [], "this": []}
    for k in range(args.rounds):
        for name, tree in trees.items():
            result = once(tree)
            runs[name].append(result)
            print(f"round {k + 1} {name}: {json.dumps(result)}", flush=True)
    keys = sorted(set(runs["other"][0]) & set(runs["this"][0]))
    for key in keys:
        other = statistics.median(r[key] for r in runs["other"])
        this = statistics.median(r[key] for r in runs["this"])
        ratio = this / other if other else float("nan")
        print(f"{key}: other {other:.3f}  this {this:.3f}  ratio {ratio:.3f}")


if __name__ == "__main__":
    main()
