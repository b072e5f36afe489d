"""In-process scenarios: a replay at full speed and the pure core."""

from __future__ import annotations

import dataclasses
import gc
import math
import tempfile
import time
from pathlib import Path


def replay_rate(commands: int = 20_000) -> dict[str, float]:
    """A replay at maximum speed, in process, everything on: a mock slave follows and the
    recorder writes MCAP. Commands per second issued and answered, on the real clock."""
    import trio

    from arena.drivers.mock_slave import MockSlave
    from arena.recording.recorder import Recorder
    from arena.recording.replay import ReplayMaster, TimedCommand
    from arena.robot.manager import open_manager
    from arena.robot.model import load_robot_model
    from arena.robot.motion import Command
    from arena.server.run import tune_garbage_collector

    model = load_robot_model("so-arm100")
    policy = dataclasses.replace(model.safety, command_rate=1e9, command_burst=10**9)
    # Recorded at 100 Hz; at the highest speed (1000x) the replay is always behind its
    # schedule, so what is measured is the work per command.
    timed = [
        TimedCommand(i * 0.01, Command.of({"Rotation": (i % 2) * 0.001})) for i in range(commands)
    ]

    async def run(folder: Path) -> dict[str, float]:
        recorder = Recorder(folder)
        async with trio.open_nursery() as recording:
            await recording.start(recorder.run)
            async with open_manager() as manager:
                manager.on_create.append(recorder.follow)
                robot = await manager.create_robot("so-arm100", robot_id="replay", policy=policy)
                slave = MockSlave()
                await robot.attach_slave(slave)
                master = ReplayMaster(timed, speed=1000.0)
                start = time.perf_counter()
                await robot.attach_master(master)
                while robot.snapshot().master is not None:
                    await trio.sleep(0.005)  # a snapshot costs ~10 us: not too often
                elapsed = time.perf_counter() - start
            recording.cancel_scope.cancel()
        return {
            "replay_commands_per_s": master.sent / elapsed,
            "replay_refused": float(master.refused),
            "replay_recorded_messages": float(recorder.writer.messages),
            "replay_recording_dropped": float(recorder.status()["dropped"]),
        }

    # The collector tuned as `arena serve` tunes it, and put back after (this process goes on
    # to run the benchmark's clients).
    thresholds = gc.get_threshold()
    tune_garbage_collector()
    try:
        with tempfile.TemporaryDirectory() as folder:
            return trio.run(run, Path(folder))
    finally:
        gc.unfreeze()
        gc.set_threshold(*thresholds)


def core_rate(count: int = 20_000) -> dict[str, float]:
    """Pure core: commands per second."""
    from arena.robot.core import RobotCore
    from arena.robot.model import load_robot_model
    from arena.robot.motion import Command

    model = load_robot_model("so-arm100")
    policy = dataclasses.replace(model.safety, command_rate=1e12, command_burst=10**9)
    core = RobotCore(model, 0.0, policy)
    commands = [Command.of({"Rotation": (i % 2) * 0.001}) for i in range(count)]
    start = time.perf_counter()
    for i, command in enumerate(commands):
        core.command(None, command, i * 0.01)
    return {"core_commands_per_s": count / (time.perf_counter() - start)}


def guard_cost(count: int = 20_000) -> dict[str, float]:
    """The collision guard's cost per command: a teleoperation stream (every joint on its own
    slow sine, 100 commands a second) through `RobotCore.command` with the guard and without,
    p50 / p99 of each call in microseconds."""
    from arena.robot.core import RobotCore
    from arena.robot.model import load_robot_model
    from arena.robot.motion import Command

    model = load_robot_model("so-arm100")
    policy = dataclasses.replace(model.safety, command_rate=1e12, command_burst=10**9)
    names = model.joint_names
    commands = [
        Command.of({n: 12.0 * math.sin(i * 0.01 * (k + 1) * 0.7) for k, n in enumerate(names)})
        for i in range(count)
    ]

    def timed(guarded: bool) -> list[float]:
        core = RobotCore(model, 0.0, policy)
        if not guarded:
            core.guard = None
        costs = []
        for i, command in enumerate(commands):
            start = time.perf_counter_ns()
            result, _ = core.command(None, command, i * 0.01)
            costs.append((time.perf_counter_ns() - start) / 1000.0)
            assert result.accepted, result.message
        return sorted(costs)

    with_guard, without = timed(True), timed(False)

    def at(costs: list[float], q: float) -> float:
        return costs[min(len(costs) - 1, int(q * len(costs)))]

    return {
        "guard_command_p50_us": at(with_guard, 0.5),
        "guard_command_p99_us": at(with_guard, 0.99),
        "unguarded_command_p50_us": at(without, 0.5),
        "unguarded_command_p99_us": at(without, 0.99),
    }


def physics_rate(seconds: float = 3.0) -> dict[str, float]:
    """The physics twin: MuJoCo steps a second flat out, and the CPU the real-time slave takes
    at its 500 Hz (stepping, reporting 100 times a second into trio), as a share of a core."""
    import trio

    from arena.drivers.physics import ArmSimulation, PhysicsSlave
    from arena.robot.manager import open_manager
    from arena.robot.model import load_robot_model

    simulation = ArmSimulation(load_robot_model("so-arm100"))
    start = time.perf_counter()
    simulation.step(5000)
    flat_out = 5000 / (time.perf_counter() - start)

    async def run() -> float:
        async with open_manager() as manager:
            robot = await manager.create_robot("so-arm100", robot_id="twin")
            await robot.attach_slave(PhysicsSlave())
            await trio.sleep(1.0)  # compiled and stepping
            cpu, wall = time.process_time(), time.perf_counter()
            await trio.sleep(seconds)
            return (time.process_time() - cpu) / (time.perf_counter() - wall)

    return {"physics_steps_per_s": flat_out, "physics_500hz_cpu_percent": 100 * trio.run(run)}


def writer_rate(events: int = 30_000) -> dict[str, float]:
    """What the recording process can write, in events a second, with and without Foxglove's
    view (transforms at most 30 a second per tree, as by default, and one per record), doing
    the child's work: records made, transforms computed, chunks compressed, file written. The
    events alternate the two trees every 10 ms. A fleet of 100 robots at 50 Hz asks for
    ~15,000 events a second."""
    from arena.recording.foxglove import Twins
    from arena.recording.mcap_file import FileSeries, McapFileWriter
    from arena.recording.writer_process import items_of_events, pack_events
    from arena.robot.events import JointStatesReceived, TargetsSent
    from arena.robot.model import load_robot_model

    names = load_robot_model("so-arm100").joint_names
    robots = {"arm": {"robot_type": "so-arm100"}}
    slices = []
    for start in range(0, events, 128):  # slices as the recorder packs them
        part: list[TargetsSent | JointStatesReceived] = []
        for i in range(start, min(start + 128, events)):
            joints = {name: (i % 90) * 0.5 for name in names}
            part.append(
                TargetsSent("arm", joints, i * 0.01, 0.0)
                if i % 2
                else JointStatesReceived("arm", "slave", joints, i * 0.01, 0.0)
            )
        slices.append(pack_events("arm", 0.0, part))

    def rate(foxglove: bool, per_second: float = 30.0) -> float:
        with tempfile.TemporaryDirectory() as scratch:
            writer = McapFileWriter(FileSeries(Path(scratch), {}, foxglove=foxglove))
            writer.robots.update(robots)
            twins = Twins(writer.robots, rate=per_second) if foxglove else None
            if twins is not None:
                writer.first_in_file = twins.introduce
                twins.twin("arm")  # the model loads once, before the clock starts
            start = time.perf_counter()
            for begin in range(0, len(slices), 4):  # batches as the recorder sends them
                writer.write(items_of_events(slices[begin : begin + 4], twins), flush=False)
            writer.close()
            return events / (time.perf_counter() - start)

    plain, viewed, every = rate(False), rate(True), rate(True, 0.0)
    return {
        "writer_events_per_s": plain,
        "writer_foxglove_events_per_s": viewed,
        "writer_foxglove_ratio": viewed / plain,
        "writer_foxglove_every_record_events_per_s": every,
    }
