"""`arena bench teleop`'s sweep: a leader arm moved the way a person moves it, the follower's goal
writes timed against it, for Arena's leader-arm teleoperation and for LeRobot's own loop.

The leader's first servo follows minimum-jerk moves (`MOVES`: sweeps and reversals of 20-60
degrees at up to 180 deg/s, and a few fast flicks), still for `REST` between them, on a
simulated bus at 1 Mbaud with wire time; the follower is another simulated bus, whose log of
Goal_Position writes to servo 1 is the follower's goal over time. The figures, the same for any
follower however many writes it makes (`summarise`):

- tracking lag: per position the leader shows while it moves (from the moment it first shows
  it), how long until the follower's goal is on that encoder step (`REACHED`); p50 and p99,
  and the positions not reached before the leader's next move;
- first reaction: from the leader's first visible change in a move (its register moved a step)
  to the follower's first write that moves toward it;
- overshoot: per move, how far the follower's goal goes past the leader's final value (degrees;
  p50 and max); and where the follower's goal ends, short of or past the leader's (end error).

The bench's process is the hardware and the hand: the two simulated buses and the leader's
moves. The teleoperation under test runs in a process of its own, its drivers paced on the
simulators (arena/servo/sim_pace.py): Arena's is an so-arm100 robot, usb-master on the leader
and usb-slave on the follower at their default rates (this file run as a script, `follow`,
from any source tree: tools/versus_tree.py runs main's so, and this file's `_follow` imports
only what every tree has); LeRobot's is `lerobot-teleoperate`'s loop (SO-101 leader and
follower, 60 fps) run by arena/bench/lerobot_teleop.py in LeRobot 0.6's Python (`make
compat`).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

STEPS_PER_DEGREE = 4096 / 360.0
CENTRE = 2048  # the servo's step at the leader's zero, for both arms
#: Human-like moves of the leader's first joint, (degrees, seconds): minimum-jerk, whose peak
#: speed is 1.875 x degrees / seconds (up to 180 deg/s), back and forth; (20, 0.15) are flicks.
MOVES: tuple[tuple[float, float], ...] = (
    (40, 0.5),
    (-60, 0.625),
    (30, 0.4),
    (-30, 0.35),
    (50, 0.55),
    (-40, 0.45),
    (20, 0.15),
    (-20, 0.15),
    (60, 0.7),
    (-50, 0.6),
) * 2
#: Seconds the leader rests after each move.
REST = 0.25
#: The follower's goal is where the leader was when on the same encoder step (degrees).
REACHED = 0.5 / STEPS_PER_DEGREE
GOAL_POSITION = 42  # the Feetech register the follower's goals are written to
#: LeRobot's side: `lerobot-teleoperate`'s default rate, and the script that runs its loop.
LEROBOT_FPS = 60
LEROBOT_SCRIPT = Path(__file__).with_name("lerobot_teleop.py")

Sample = tuple[float, float]  # (monotonic seconds, degrees)


@dataclass(frozen=True)
class Move:
    """One of the leader's moves: `start` when its register first changed, `end` when it got to
    `target` (degrees) from `origin`."""

    start: float
    end: float
    origin: float
    target: float


@dataclass
class Sweep:
    """What one run recorded: the leader's path, its moves, the follower's goal writes."""

    path: list[Sample] = field(default_factory=list)
    moves: list[Move] = field(default_factory=list)
    writes: list[Sample] = field(default_factory=list)


def minimum_jerk(f: float) -> float:
    """The minimum-jerk profile, 0 to 1 as `f` goes 0 to 1 (a person's reaching motion)."""
    return f * f * f * (10 - 15 * f + 6 * f * f)


def _steps(degrees: float) -> int:
    return round(CENTRE + degrees * STEPS_PER_DEGREE)


def _degrees(steps: float) -> float:
    return (steps - CENTRE) / STEPS_PER_DEGREE


# -- the figures ------------------------------------------------------------------------------


def _window(moves: Sequence[Move], k: int, writes: Sequence[Sample]) -> float:
    """Until when move k's figures look: the next move's start (or the last write)."""
    if k + 1 < len(moves):
        return moves[k + 1].start
    return writes[-1][0] if writes else moves[k].end


def reach_lags(sweep: Sweep, tolerance: float = REACHED) -> list[float | None]:
    """Per position the leader shows while it moves (from the moment it first shows it):
    seconds until the follower's goal gets there (within `tolerance` degrees, coming the way
    the leader goes), None if not before the leader's next move."""
    lags: list[float | None] = []
    times = [t for t, _ in sweep.writes]
    for k, move in enumerate(sweep.moves):
        until = _window(sweep.moves, k, sweep.writes)
        up = move.target > move.origin
        shown: float | None = None
        w = 0
        for t, x in sweep.path:
            if not move.start <= t <= move.end or x == shown:
                continue
            shown = x
            while w < len(times) and times[w] < t:
                w += 1
            lag = None
            for tw, value in sweep.writes[w:]:
                if tw > until:
                    break
                if (value >= x - tolerance) if up else (value <= x + tolerance):
                    lag = tw - t
                    break
            lags.append(lag)
    return lags


def first_reactions(sweep: Sweep, tolerance: float = REACHED / 2) -> list[float | None]:
    """Per move: seconds from the leader's first change to the follower's first write that
    moves its goal toward the leader's target (by more than `tolerance`), None if none."""
    reactions: list[float | None] = []
    for k, move in enumerate(sweep.moves):
        until = _window(sweep.moves, k, sweep.writes)
        before = [v for t, v in sweep.writes if t < move.start]
        was = before[-1] if before else move.origin
        sign = 1.0 if move.target > move.origin else -1.0
        reactions.append(
            next(
                (
                    t - move.start
                    for t, v in sweep.writes
                    if move.start <= t <= until and (v - was) * sign > tolerance
                ),
                None,
            )
        )
    return reactions


def overshoots(sweep: Sweep) -> list[float]:
    """Per move: degrees the follower's goal went past the leader's final value (0 if never)."""
    out = []
    for k, move in enumerate(sweep.moves):
        until = _window(sweep.moves, k, sweep.writes)
        sign = 1.0 if move.target > move.origin else -1.0
        past = [(v - move.target) * sign for t, v in sweep.writes if move.start <= t <= until]
        out.append(max([0.0, *past]))
    return out


def end_errors(sweep: Sweep) -> list[float]:
    """Per move: degrees between the follower's last goal before the next move and the
    leader's final value (where the follower settled against where the leader did)."""
    out = []
    for k, move in enumerate(sweep.moves):
        until = _window(sweep.moves, k, sweep.writes)
        last = [v for t, v in sweep.writes if t <= until]
        out.append(abs(last[-1] - move.target) if last else float("nan"))
    return out


def summarise(sweep: Sweep, prefix: str) -> dict[str, float]:
    """The figures of one run, named `{prefix}_...` (milliseconds and degrees)."""
    from arena.bench.common import percentile

    lags = reach_lags(sweep)
    reached = [lag for lag in lags if lag is not None]
    reactions = first_reactions(sweep)
    reacted = [r for r in reactions if r is not None]
    over = overshoots(sweep)
    ends = end_errors(sweep)
    return {
        f"{prefix}_lag_p50_ms": 1000 * percentile(reached, 0.5),
        f"{prefix}_lag_p99_ms": 1000 * percentile(reached, 0.99),
        f"{prefix}_lag_samples": float(len(lags)),
        f"{prefix}_unreached_samples": float(len(lags) - len(reached)),
        f"{prefix}_first_reaction_p50_ms": 1000 * percentile(reacted, 0.5),
        f"{prefix}_first_reaction_p99_ms": 1000 * percentile(reacted, 0.99),
        f"{prefix}_no_reaction_moves": float(len(reactions) - len(reacted)),
        f"{prefix}_overshoot_p50_deg": percentile(over, 0.5),
        f"{prefix}_overshoot_max_deg": max(over, default=float("nan")),
        f"{prefix}_end_error_p50_deg": percentile(ends, 0.5),
        f"{prefix}_end_error_max_deg": max(ends, default=float("nan")),
        f"{prefix}_goal_writes": float(len(sweep.writes)),
    }


# -- the runs ---------------------------------------------------------------------------------


async def drive_leader(
    leader: Any, sweep: Sweep, moves: Sequence[tuple[float, float]], rest: float = REST
) -> None:
    """Move the leader's servo 1 by hand along `moves` (a `PtySimBus`), still for `rest` after
    each, recording its path and moves into `sweep`; about 500 samples a second."""
    import trio

    x = 0.0
    for amount, span in moves:
        began = time.monotonic()
        shown = _steps(x)
        start: float | None = None
        while True:
            f = min(1.0, (time.monotonic() - began) / span)
            steps = _steps(x + amount * minimum_jerk(f))
            with leader.paused() as bus:
                bus.servo(1).move_by_hand(steps)
                now = time.monotonic()
            if steps != shown and start is None:
                start = now
            sweep.path.append((now, _degrees(steps)))
            if f >= 1.0:
                break
            await trio.sleep(0.002)
        sweep.moves.append(Move(start or now, now, _degrees(_steps(x)), _degrees(steps)))
        x += amount
        await trio.sleep(rest)


def _follower_writes(log: list[tuple[float, int, int, bytes]]) -> list[Sample]:
    from arena.feetech import registers as reg

    return [
        (t, _degrees(reg.GOAL_POSITION.decode(data)))
        for t, sid, address, data in log
        if sid == 1 and address == GOAL_POSITION
    ]


def _run_follower(
    command: list[str],
    env: dict[str, str],
    moves: Sequence[tuple[float, float]],
    rest: float = REST,
) -> Sweep:
    """Two simulated buses; `command` (given the leader's and the follower's ports) connects a
    teleoperation to them in a process of its own, prints `ready` and runs until a line on its
    stdin; meanwhile the leader is moved along `moves` and the follower's goal writes logged.
    `FollowerFailed` if it does not get ready or ends before the sweep does."""
    import trio

    from arena.feetech.sim import SimBus
    from arena.servo.sim_pty import PtySimBus

    sweep = Sweep()

    async def run(leader: PtySimBus, follower: PtySimBus, folder: Path) -> None:
        log: list[tuple[float, int, int, bytes]] = []
        errors = open(folder / "stderr", "w+b")  # noqa: SIM115 (read back on failure)
        process = subprocess.Popen(
            [*command, str(leader.link), str(follower.link), str(folder)],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=errors,
            text=True,
            env=env,
        )
        try:
            assert process.stdin is not None and process.stdout is not None
            while (line := await trio.to_thread.run_sync(process.stdout.readline)) != "ready\n":
                if not line:  # (imports take seconds on a loaded machine: no timeout here)
                    raise FollowerFailed(f"it did not start: {_tail(errors)}")
            await trio.sleep(0.5)
            with follower.paused() as bus:
                bus.write_log = log
            await drive_leader(leader, sweep, moves, rest)
            await trio.sleep(0.1)  # the follower's last writes
            with follower.paused() as bus:
                bus.write_log = None
            if process.poll() is not None:
                raise FollowerFailed(f"it stopped during the sweep: {_tail(errors)}")
            process.stdin.write("stop\n")
            process.stdin.flush()
            await trio.to_thread.run_sync(process.wait, 60)
        finally:
            if process.poll() is None:
                process.kill()
                process.wait()
            errors.close()
        sweep.writes = _follower_writes(log)

    with (
        tempfile.TemporaryDirectory() as name,
        PtySimBus(Path(name) / "leader", SimBus(), wire_time=True, share=True) as leader,
        PtySimBus(Path(name) / "follower", SimBus(), wire_time=True, share=True) as follower,
    ):
        trio.run(run, leader, follower, Path(name))
    return sweep


class FollowerFailed(RuntimeError):
    """A teleoperation did not start, or ended before the sweep did (its message says why)."""


def _tail(errors: Any) -> str:
    errors.seek(0)
    lines = errors.read().decode(errors="replace").strip().splitlines()
    return " | ".join(lines[-3:]) or "(nothing on stderr)"


def arena_sweep(
    moves: Sequence[tuple[float, float]] = MOVES, rest: float = REST, tree: Path | None = None
) -> Sweep:
    """Arena's leader-arm teleoperation (an so-arm100 robot, usb-master on the leader and
    usb-slave on the follower at their default rates) in a process of its own, run from the
    source `tree` (default: the one this file is in), the leader moved along `moves`."""
    root = tree or Path(__file__).resolve().parents[2]
    env = {**os.environ, "PYTHONPATH": str(root)}
    # -P: the script's folder (arena/bench) is not put on the path; `tree`'s arena is imported.
    return _run_follower([sys.executable, "-P", __file__, "follow"], env, moves, rest)


def _follow(leader_port: str, follower_port: str) -> None:
    """`_run_follower`'s command for Arena: a robot on the two ports until a line on stdin."""
    import trio

    from arena.drivers.config import UsbMasterConfig, UsbSlaveConfig
    from arena.drivers.usb_master import UsbMaster
    from arena.drivers.usb_slave import UsbSlave
    from arena.robot.manager import open_manager
    from arena.robot.model import load_robot_model

    async def run() -> None:
        model = load_robot_model("so-arm100")
        async with open_manager() as manager:
            robot = await manager.create_robot("so-arm100", robot_id="arm")
            await robot.attach_slave(UsbSlave(UsbSlaveConfig(port=follower_port), model))
            master = UsbMaster(UsbMasterConfig(port=leader_port), model)
            await master.prepare()
            await robot.attach_master(master)
            print("ready", flush=True)
            await trio.to_thread.run_sync(sys.stdin.readline, abandon_on_cancel=True)

    trio.run(run)


def compat_python() -> Path | None:
    """LeRobot 0.6's Python (`make compat`: .compat/python beside this checkout, or the one
    ARENA_COMPAT_PYTHON names), or None when there is none."""
    named = os.environ.get("ARENA_COMPAT_PYTHON")
    path = Path(named) if named else Path(__file__).resolve().parents[2] / ".compat" / "python"
    return path if path.exists() else None


def lerobot_sweep(
    python: Path,
    moves: Sequence[tuple[float, float]] = MOVES,
    rest: float = REST,
    fps: int = LEROBOT_FPS,
) -> Sweep:
    """LeRobot's teleoperation loop (`LEROBOT_SCRIPT` in LeRobot's `python`, at `fps`), the
    leader moved along `moves`."""
    command = [str(python), str(LEROBOT_SCRIPT), str(fps)]
    return _run_follower(command, dict(os.environ), moves, rest)


def teleop_versus(
    moves: Sequence[tuple[float, float]] = MOVES, python: Path | None = None
) -> dict[str, float]:
    """The sweep for Arena, then for LeRobot in `python` (default: `compat_python()`; without
    one, or when it fails, said and skipped), and Arena's figure over LeRobot's for the lag and
    the first reaction (ratios: below 1, Arena is ahead)."""
    results = summarise(arena_sweep(moves), "teleop_sweep_arena")
    python = python or compat_python()
    how = "`make compat` builds .compat/python; or name one with --lerobot-python"
    if python is None or not python.exists():
        print(f"teleop: LeRobot's loop skipped: no LeRobot 0.6 Python ({how})", flush=True)
        return results
    try:
        theirs = summarise(lerobot_sweep(python, moves), "teleop_sweep_lerobot")
    except FollowerFailed as failed:
        print(f"teleop: LeRobot's loop failed in {python}: {failed} ({how})", flush=True)
        return results
    results.update(theirs)
    for key in ("lag_p50_ms", "lag_p99_ms", "first_reaction_p50_ms", "first_reaction_p99_ms"):
        mine, other = results[f"teleop_sweep_arena_{key}"], theirs[f"teleop_sweep_lerobot_{key}"]
        results[f"teleop_sweep_ratio_{key}"] = mine / other if other else float("nan")
    return results


def main() -> None:
    """`follow LEADER FOLLOWER FOLDER`: Arena's side of the sweep (`arena_sweep` runs it)."""
    if sys.argv[1:2] == ["follow"]:
        _follow(sys.argv[2], sys.argv[3])
    else:
        print(json.dumps(summarise(arena_sweep(), "teleop_sweep_arena")))


if __name__ == "__main__":
    main()
