"""`arena bench teleop`'s sweep (arena/bench/teleop.py): its figures on made-up runs whose
answers are known, and a short sweep through the real drivers on two simulated buses (figures
that exist and make sense; how fast is the benchmark's business, not a test's)."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from arena.bench import teleop
from arena.bench.teleop import Move, Sweep

SPAN = 0.5  # seconds of a made-up 40-degree move
TICK = 0.002  # its leader samples


def leader(origin: float, target: float, start: float) -> tuple[list[tuple[float, float]], Move]:
    """A made-up minimum-jerk leader path, on encoder steps as the bench records it."""
    path = []
    for k in range(round(SPAN / TICK) + 1):
        f = k * TICK / SPAN
        steps = teleop._steps(origin + (target - origin) * teleop.minimum_jerk(f))
        path.append((start + k * TICK, teleop._degrees(steps)))
    moved = next(t for t, x in path if x != path[0][1])
    return path, Move(moved, path[-1][0], path[0][1], path[-1][1])


def two_moves() -> Sweep:
    """40 degrees out, 1 s still, and back; no follower writes yet."""
    out, first = leader(0.0, 40.0, 10.0)
    back, second = leader(first.target, 0.0, 11.5)
    return Sweep(path=out + back, moves=[first, second])


def lagging(sweep: Sweep, lag: float) -> list[tuple[float, float]]:
    """A follower that writes what the leader showed, `lag` seconds later."""
    return [(t + lag, x) for t, x in sweep.path]


def test_a_follower_behind_by_a_known_lag_is_measured_at_that_lag() -> None:
    sweep = two_moves()
    sweep.writes = lagging(sweep, 0.020)
    lags = teleop.reach_lags(sweep)
    assert lags and all(lag == pytest.approx(0.020, abs=1e-9) for lag in lags)
    # Each position counted once, when the leader first showed it: not once a sample.
    shown = {x for t, x in sweep.path if sweep.moves[0].start <= t <= sweep.moves[0].end}
    assert len(lags) == 2 * len(shown)  # (each move shows every value but where it began)
    assert teleop.first_reactions(sweep) == [pytest.approx(0.020, abs=1e-9)] * 2
    assert teleop.overshoots(sweep) == [0.0, 0.0]
    assert teleop.end_errors(sweep) == [0.0, 0.0]
    figures = teleop.summarise(sweep, "x")
    assert figures["x_lag_p50_ms"] == pytest.approx(20.0)
    assert figures["x_lag_p99_ms"] == pytest.approx(20.0)
    assert figures["x_unreached_samples"] == 0
    assert figures["x_first_reaction_p50_ms"] == pytest.approx(20.0)


def test_a_follower_that_writes_the_same_goal_many_times_is_not_counted_more() -> None:
    once, many = two_moves(), two_moves()
    once.writes = lagging(once, 0.010)
    many.writes = sorted(
        [*lagging(many, 0.010), *((t + 0.004, x) for t, x in lagging(many, 0.010))]
    )
    assert teleop.reach_lags(many) == teleop.reach_lags(once)


def test_an_overshoot_of_a_known_size_is_measured_and_where_it_settles() -> None:
    sweep = two_moves()
    writes = [(t, x) for t, x in lagging(sweep, 0.010) if t <= sweep.moves[0].end + 0.010]
    end, target = sweep.moves[0].end + 0.010, sweep.moves[0].target
    # Past the leader's 40 degrees by 2.5 on the way out, then back to 0.5 short of it.
    writes += [(end + 0.01, target + 1), (end + 0.02, target + 2.5), (end + 0.05, target - 0.5)]
    sweep.writes = sorted(writes)
    assert teleop.overshoots(sweep)[0] == pytest.approx(2.5)
    assert teleop.end_errors(sweep)[0] == pytest.approx(0.5)
    figures = teleop.summarise(sweep, "x")
    assert figures["x_overshoot_max_deg"] == pytest.approx(2.5)


def test_a_follower_that_stops_short_leaves_the_last_positions_unreached() -> None:
    sweep = two_moves()
    target = sweep.moves[0].target
    # The first move followed 5 ms behind, but never past 39.5 degrees; nothing comes back.
    sweep.writes = [(t + 0.005, min(x, target - 0.5)) for t, x in sweep.path if x > 0 or t < 11]
    sweep.writes = [w for w in sweep.writes if w[0] < sweep.moves[1].start]
    lags = teleop.reach_lags(sweep)
    first = [lag for lag in lags[: len(lags) // 2 + 1] if lag is not None]
    assert all(lag == pytest.approx(0.005, abs=1e-9) for lag in first)
    unreached = teleop.summarise(sweep, "x")["x_unreached_samples"]
    assert unreached > 0  # the positions above 39.5 on the way out, and the whole way back
    assert teleop.first_reactions(sweep)[1] is None


def test_a_short_sweep_through_the_real_drivers_reaches_every_position() -> None:
    """Arena's usb-master and usb-slave (their own process) on two simulated buses."""
    moves = [(30.0, 0.4), (-30.0, 0.35), (20.0, 0.15)]
    sweep = teleop.arena_sweep(moves, rest=1.0)  # a long rest: a loaded machine catches up
    assert [round(m.target - m.origin) for m in sweep.moves] == [30, -30, 20]
    assert sweep.writes, "the follower was written no goal"
    figures = teleop.summarise(sweep, "arena")
    assert figures["arena_lag_samples"] > 10  # (fewer, the more a loaded machine delays the hand)
    assert figures["arena_unreached_samples"] == 0
    assert figures["arena_no_reaction_moves"] == 0
    assert 0 < figures["arena_lag_p50_ms"] <= figures["arena_lag_p99_ms"]
    assert figures["arena_first_reaction_p50_ms"] > 0
    assert 0 <= figures["arena_overshoot_p50_deg"] <= figures["arena_overshoot_max_deg"] < 30
    assert math.isfinite(figures["arena_end_error_max_deg"])


def test_without_lerobots_python_arenas_figures_come_and_lerobots_are_skipped_with_a_hint(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    figures = teleop.teleop_versus([(30.0, 0.4)], python=tmp_path / "no-python")
    assert figures["teleop_sweep_arena_lag_samples"] > 0
    assert not [key for key in figures if "lerobot" in key or "ratio" in key]
    said = capsys.readouterr().out
    assert "LeRobot's loop skipped" in said and "make compat" in said


def test_a_lerobot_python_that_cannot_run_the_loop_is_said_not_raised(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    python = tmp_path / "python"  # a LeRobot without its feetech extra fails like this
    python.write_text("#!/bin/sh\necho 'No module named scservo_sdk' >&2\nexit 1\n")
    python.chmod(0o755)
    figures = teleop.teleop_versus([(30.0, 0.4)], python=python)
    assert not [key for key in figures if "lerobot" in key]
    said = capsys.readouterr().out
    assert "LeRobot's loop failed" in said and "No module named scservo_sdk" in said
