"""A policy master's rollout strategies (specs/policy.md, "Rollout strategies") on trio's
MockClock, with the stand-in worker of tests/test_policy_master.py: `episodic` makes N
episodes of T seconds and takes the robot back to its start pose between them at the join
speed with the policy paused (never reloaded), then ends the master; `sentry` starts a new
episode every T seconds; `highlight` makes an episode only when asked, of the last N
seconds. tests/test_strategies_server.py runs them through a real server and LeRobot."""

from __future__ import annotations

import itertools
from typing import Any

import pytest
import trio
from trio.testing import MockClock

from arena.policy.master import PolicyMaster
from arena.policy.strategy import Episodic, Highlight, Sentry
from arena.protocol.errors import ArenaError, ErrorCode
from arena.robot.events import CommandHandled, EpisodeChanged, FaultReported, RobotEvent
from arena.robot.handle import Robot
from arena.robot.manager import RobotManager
from tests.test_policy_master import IDENTITY, PERIOD, FakeWorker, arm, attach


def drift(observation: Any) -> list[tuple[float, ...]]:
    """Ten actions that turn the base further and further (2 degrees a step) from where it
    is: a policy that moves the arm away from its start pose."""
    base, *rest = observation.state
    return [(base + 2.0 * (step + 1), *rest) for step in range(10)]


def episodes(events: list[RobotEvent]) -> list[tuple[str, int, float]]:
    """The episode marks: (change, index, time)."""
    return [(e.change, e.index, e.time) for e in events if isinstance(e, EpisodeChanged)]


def base_of(robot: Robot) -> float:
    return next(
        j.virtual_value for j in robot.snapshot().joints if j.name == robot.model.joints[0].name
    )


async def until_gone(robot: Robot) -> None:
    with trio.fail_after(600):
        while robot.snapshot().master is not None:
            await trio.sleep(0.1)


async def test_episodic_makes_n_episodes_resets_between_them_and_ends(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    robot, slave = await arm(manager)
    worker = FakeWorker(drift)
    start = base_of(robot)
    strategy = Episodic(3, 2.0, "reach", reset_s=30.0)
    with robot.subscribe(kinds=[EpisodeChanged, CommandHandled]) as queue:
        master = await attach(robot, worker, strategy=strategy)  # type: ignore[arg-type]
        attached = trio.current_time()
        await until_gone(robot)
        seen = queue.drain()
    marks = episodes(seen)
    assert [(c, i) for c, i, _ in marks] == [
        ("start", 0),
        ("stop", 0),
        ("start", 1),
        ("stop", 1),
        ("start", 2),
        ("stop", 2),
    ]
    times = [t for _, _, t in marks]
    assert times[0] == pytest.approx(attached, abs=PERIOD)
    for begin, end in zip(times[::2], times[1::2], strict=True):
        assert end - begin == pytest.approx(2.0)  # each episode lasts T
    # The master ended after the last; its worker was loaded once and stopped.
    assert master.counters.loads == 1 and worker.closed
    assert master.counters.resets == 2
    commands = [e for e in seen if isinstance(e, CommandHandled)]
    assert all(c.source == IDENTITY for c in commands)
    for stop_time, start_time in ((times[1], times[2]), (times[3], times[4])):
        reset = [c for c in commands if stop_time < c.time <= start_time]
        # Between two episodes: the robot taken back to the base's start at the join speed,
        # never faster, and no observation of the policy's meanwhile (it is paused).
        assert reset, "no reset motion"
        values = [dict((g.name, g.value) for g in c.command.joints) for c in reset]
        name = robot.model.joints[0].name
        bases = [v[name] for v in values]
        step = robot.model.safety.join_speed * PERIOD
        assert all(abs(b - a) <= step + 1e-9 for a, b in itertools.pairwise(bases))
        assert bases[-1] == pytest.approx(start)
        asked = [at for at, _ in worker.observations if stop_time + PERIOD < at < start_time]
        assert asked == []
    # The policy drove away from the start in each episode (the reset had work to do).
    assert max(abs(t[1].get(robot.model.joints[0].name, start) - start) for t in slave.targets) > 5


async def test_a_start_pose_is_where_each_reset_goes(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    robot, _ = await arm(manager)
    name = robot.model.joints[0].name
    strategy = Episodic(2, 1.0, "reach", reset_s=30.0, start_pose={name: 20.0})
    with robot.subscribe(kinds=[EpisodeChanged, CommandHandled]) as queue:
        await attach(robot, FakeWorker(), strategy=strategy)  # type: ignore[arg-type]
        await until_gone(robot)
        seen = queue.drain()
    stop, start = [t for c, _, t in episodes(seen)][1:3]
    reset = [e for e in seen if isinstance(e, CommandHandled) and stop < e.time <= start]
    assert {g.name for g in reset[-1].command.joints} == {name}
    assert reset[-1].command.joints[0].value == pytest.approx(20.0)


async def test_a_reset_that_runs_out_of_time_says_so_and_the_next_episode_starts(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    robot, _ = await arm(manager)
    name = robot.model.joints[0].name
    # 90 degrees at the join speed (15 deg/s) take 6 s; the reset has 1.
    strategy = Episodic(2, 1.0, "reach", reset_s=1.0, start_pose={name: 90.0})
    with robot.subscribe(kinds=[EpisodeChanged, FaultReported]) as queue:
        await attach(robot, FakeWorker(), strategy=strategy)  # type: ignore[arg-type]
        await until_gone(robot)
        seen = queue.drain()
    faults = [e for e in seen if isinstance(e, FaultReported) and not e.cleared]
    assert [f.code for f in faults] == [ErrorCode.POSE_NOT_REACHED]
    times = [t for _, _, t in episodes(seen)]
    assert len(times) == 4 and times[2] - times[1] == pytest.approx(1.0, abs=2 * PERIOD)


async def test_sentry_starts_an_episode_every_t_seconds_and_stops_the_last_at_detach(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    robot, _ = await arm(manager)
    with robot.subscribe(kinds=[EpisodeChanged]) as queue:
        master = await attach(
            robot,
            FakeWorker(),
            strategy=Sentry(1.5, "watch"),  # type: ignore[arg-type]
        )
        await trio.sleep(4.0)
        await robot.detach_master(master.master_id)
        await trio.sleep(0.5)
        marks = episodes(queue.drain())
    assert [(c, i) for c, i, _ in marks] == [
        ("start", 0),
        ("stop", 0),
        ("start", 1),
        ("stop", 1),
        ("start", 2),
        ("stop", 2),
    ]
    times = [t for _, _, t in marks]
    assert times[1] - times[0] == pytest.approx(1.5) and times[3] - times[2] == pytest.approx(1.5)
    assert times[2] == times[1]  # back to back
    assert robot.episodes.active is None and robot.episodes.kept == 3
    assert master.figures()["episodes"] == 3


async def test_highlight_keeps_the_last_seconds_only_when_asked(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    robot, _ = await arm(manager)
    saved: list[float] = []
    kept: list[float] = []

    class Keeper:
        def keep(self, seconds: float) -> None:
            kept.append(seconds)

        def release(self) -> None:
            kept.append(-1.0)

        async def save(self, since: float, until: float) -> None:
            saved.append(since)

    with robot.subscribe(kinds=[EpisodeChanged]) as queue:
        worker = FakeWorker()

        async def start() -> FakeWorker:
            return worker

        from pathlib import Path

        from arena.policy.master import PolicySettings
        from tests.test_policy_master import FPS, frames

        master = PolicyMaster(
            PolicySettings(Path("unused"), fps=FPS, strategy=Highlight(2.0, "a good grasp")),
            robot.model,
            frames(("front",)),
            start,
        )
        master.keeper = Keeper()
        await master.prepare()
        await robot.attach_master(master, master_id=master.master_id)
        began = trio.current_time()
        await trio.sleep(1.0)
        assert episodes(queue.drain()) == []  # nothing is an episode by itself
        first = await master.highlight()  # only 1 s ran: the episode is that second
        assert first.started == pytest.approx(began, abs=PERIOD) and first.task == "a good grasp"
        await trio.sleep(5.0)
        second = await master.highlight()
        now = trio.current_time()
        assert second.started == pytest.approx(now - 2.0) and second.ended == now
        third = await master.highlight()  # at once again: starts where the last ended
        assert third.started == second.ended
        marks = episodes(queue.drain())
        await robot.detach_master(master.master_id)
        await trio.sleep(0.5)  # (the driver's task ends after the detach)
    # Each highlight is marked where it began, in the past, and where it ended.
    assert marks[:2] == [("start", 0, first.started), ("stop", 0, first.ended)]
    assert marks[2:4] == [("start", 1, second.started), ("stop", 1, second.ended)]
    assert saved == [first.started, second.started, third.started]
    assert kept == [2.0, -1.0]  # kept from the start, released at the end
    assert robot.episodes.kept == 3


async def test_a_highlight_of_a_policy_without_the_strategy_is_refused(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    robot, _ = await arm(manager)
    master = await attach(robot, FakeWorker())
    with pytest.raises(ArenaError) as plain:
        await master.highlight()
    assert plain.value.code is ErrorCode.NO_HIGHLIGHT
    await robot.detach_master(master.master_id)
    sentry = await attach(robot, FakeWorker(), strategy=Sentry(5.0, "watch"))  # type: ignore[arg-type]
    await trio.sleep(0.1)
    with pytest.raises(ArenaError) as other:
        await sentry.highlight()
    assert other.value.code is ErrorCode.NO_HIGHLIGHT and "sentry" in other.value.message


async def test_an_intervention_pauses_the_policy_and_the_episode_goes_on(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    robot, _ = await arm(manager)
    with robot.subscribe(kinds=[EpisodeChanged]) as queue:
        master = await attach(
            robot,
            FakeWorker(),
            strategy=Sentry(3.0, "watch"),  # type: ignore[arg-type]
        )
        await trio.sleep(1.0)
        link = await robot.connect_master("operator:test", kind="operator", intervene=True)
        await trio.sleep(1.0)
        assert master.counters.pauses == 1 and robot.episodes.active is not None
        await robot.end_intervention()
        await trio.sleep(1.5)
        marks = episodes(queue.drain())
        del link
    times = [t for _, _, t in marks]
    assert [(c, i) for c, i, _ in marks] == [("start", 0), ("stop", 0), ("start", 1)]
    assert times[1] - times[0] == pytest.approx(3.0)
    assert master.counters.loads == 1
