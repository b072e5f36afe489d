"""The bus worker's thread between two cycles: goals and jobs are taken when they come, not at
the next cycle (arena/servo/worker.py), on the simulated Feetech bus."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import pytest

from arena.servo.interface import ServoBus
from arena.servo.sim_pty import PtySimBus
from arena.servo.worker import BusWorker, Reading, WorkerEvent, WorkerSettings
from tests.hardware import open_test_bus, running_sim, servo_goals

#: Cycles a second: one cycle, then none for 100 s; what happens in between is the wake's.
SLOW = 0.01
#: Seconds to wait for what a working worker does at once (never reached when it works).
PATIENCE = 30.0


@pytest.fixture
def sim(tmp_path: Path) -> Iterator[PtySimBus]:
    yield from running_sim(tmp_path)


class Recorder:
    """The worker's listener: counts readings, and the goals written (by wrapping the bus)."""

    def __init__(self) -> None:
        self.readings = 0
        self.read = threading.Event()
        self.written: list[dict[int, int]] = []
        self.wrote = threading.Event()

    def reading(self, reading: Reading) -> None:
        self.readings += 1
        self.read.set()

    def event(self, event: WorkerEvent) -> None:
        pass

    def bus(self, port: str) -> ServoBus:
        bus = open_test_bus(port)
        write = bus.write_goals

        def recorded(goals: Mapping[int, int]) -> None:
            write(goals)
            self.written.append(dict(goals))
            self.wrote.set()

        bus.write_goals = recorded  # type: ignore[method-assign]
        return bus


def started(sim: PtySimBus, recorder: Recorder) -> BusWorker:
    ids = sorted(servo_goals(sim))
    worker = BusWorker(
        lambda: recorder.bus(str(sim.link)), ids, recorder, WorkerSettings(rate=SLOW)
    )
    worker.start()
    worker.first_connect.result(PATIENCE)
    assert recorder.read.wait(PATIENCE), "the first cycle's reading"
    recorder.written.clear()  # (the connection's hold: goal = present)
    recorder.wrote.clear()
    return worker


def test_goals_set_between_cycles_are_written_when_they_come(sim: PtySimBus) -> None:
    recorder = Recorder()
    worker = started(sim, recorder)
    try:
        first = sorted(servo_goals(sim))[0]
        goal = servo_goals(sim)[first] + 100
        worker.set_goals({first: goal})
        # Written long before the next cycle (100 s away): the write is the wake's.
        assert recorder.wrote.wait(PATIENCE), "the goal written before the next cycle"
        assert worker.stats.cycles <= 1  # (the first may still be counting itself)
        assert recorder.written == [{first: goal}]
        # (a sync write has no reply: the simulator takes it when it reads the port)
        deadline = time.monotonic() + PATIENCE
        while servo_goals(sim)[first] != goal and time.monotonic() < deadline:
            time.sleep(0.01)
        assert servo_goals(sim)[first] == goal
    finally:
        worker.stop()
    assert not worker._thread.is_alive()  # the stop wakes the wait too


def test_a_job_between_cycles_runs_when_submitted(sim: PtySimBus) -> None:
    recorder = Recorder()
    worker = started(sim, recorder)
    try:
        ids = sorted(servo_goals(sim))
        present: Any = worker.submit(lambda bus: bus.read_positions(ids)[0]).result(PATIENCE)
        assert set(present) == set(ids)
        assert worker.stats.cycles <= 1
    finally:
        worker.stop()


def test_goals_that_come_faster_than_one_write_between_cycles_merge(sim: PtySimBus) -> None:
    # At most one write between two cycles: a flood of goals is written once there and the
    # newest of every servo at the next cycle, never one write each.
    recorder = Recorder()
    worker = started(sim, recorder)
    try:
        first = sorted(servo_goals(sim))[0]
        base = servo_goals(sim)[first]
        worker.set_goals({first: base + 1})
        assert recorder.wrote.wait(PATIENCE)
        for k in range(2, 50):
            worker.set_goals({first: base + k})
        # the pending goals are not written before the next cycle, 100 s away
        submitted = worker.submit(lambda bus: None)
        submitted.result(PATIENCE)  # (a job run after the floods' wakes: they were all seen)
        assert recorder.written == [{first: base + 1}]
    finally:
        worker.stop()
