"""Recording to MCAP and back: schemas, deterministic replay, replay master, bad files, tools."""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import io
import itertools
import json
import os
import re
import signal
import sys
import threading
import time
from collections.abc import AsyncIterator
from functools import partial
from pathlib import Path
from typing import IO, Any

import httpx
import jsonschema
import msgspec
import pytest
import trio
from mcap.reader import NonSeekingReader, make_reader
from trio.testing import MockClock

from arena import cli
from arena.drivers.sequence_master import SequenceMaster
from arena.drivers.sequences import get_sequence
from arena.protocol.errors import ArenaError, ErrorCode, Severity
from arena.recording import mcap_file
from arena.recording.analysis import export, summarize, timeline
from arena.recording.mcap_file import FileSeries, read_recording, write_recording
from arena.recording.mcap_writer import ChunkedWriter
from arena.recording.recorder import Backoff, Recorder, check_name
from arena.recording.records import record_of
from arena.recording.replay import ReplayMaster, TimedCommand, recorded_commands
from arena.recording.writer_process import McapWriterProcess, items_of_events, pack_events
from arena.robot.events import (
    CommandHandled,
    FaultReported,
    JointStatesReceived,
    PeerChanged,
    RobotEvent,
    StateChanged,
    TargetsSent,
)
from arena.robot.handle import Robot
from arena.robot.manager import RobotManager, open_manager
from arena.robot.model import load_robot_model
from arena.robot.motion import Clamp, Command, CommandResult, JointGoal
from arena.robot.safety import Mode
from tests.conftest import RecordingSlave, RunningServer, eventually
from tests.scenarios import behaviour, record_scenario, replay_session

GOLDEN = Path(__file__).resolve().parent.parent / "recordings" / "golden"
SPEC_SCHEMAS = Path(__file__).resolve().parent.parent / "specs" / "schemas"


async def session_scenario(robot: Robot) -> None:
    """A session worth replaying: manual commands, a sequence, an e-stop and a reset."""
    await robot.command(Command.of({"Rotation": 45.0, "Pitch": -30.0}))
    await trio.sleep(1.0)
    await robot.command(Command.of({"Elbow": -20.0}, duration=0.5))
    await trio.sleep(1.0)
    await robot.attach_master(SequenceMaster([get_sequence("gentle-wave")]))
    await trio.sleep(2.5)
    await robot.estop("test stop")
    await trio.sleep(0.5)
    await robot.command(Command.of({"Rotation": 0.0}))  # refused: e-stopped
    await robot.reset()
    await trio.sleep(0.3)
    await robot.command(Command.of({"Rotation": 10.0, "Jaw": 500.0}))  # clamped
    await trio.sleep(2.0)


async def record_session(folder: Path) -> Path:
    (path,) = await record_scenario(folder, session_scenario)
    return path


@pytest.fixture
async def session_file(autojump_clock: MockClock, tmp_path: Path) -> AsyncIterator[Path]:
    yield await record_session(tmp_path)


async def test_round_trip_through_the_mcap_reader(
    autojump_clock: MockClock, session_file: Path
) -> None:
    with open(session_file, "rb") as stream:
        reader = make_reader(stream)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        topics = {channel.topic for channel in summary.channels.values()}
        messages = list(reader.iter_messages())
        metadata = {m.name: m.metadata for m in reader.iter_metadata()}
    assert {
        "/robots/arm/command",
        "/robots/arm/targets",
        "/robots/arm/joint_states",
        "/robots/arm/state",
        "/robots/arm/peer",
    } <= topics
    assert summary.statistics.message_count == len(messages) > 100
    for channel in summary.channels.values():  # Arena's records JSON, Foxglove's protobuf
        schema = summary.schemas[channel.schema_id]
        foxglove_view = channel.topic.endswith(("/tf", "/scene", "/log"))
        assert schema.encoding == ("protobuf" if foxglove_view else "jsonschema")
        assert channel.message_encoding == ("protobuf" if foxglove_view else "json")
    assert metadata["arena"]["server"] == "arena"
    assert '<robot name="so-arm100">' in metadata["robot/arm"]["urdf"]
    recording = read_recording(session_file)
    assert not recording.truncated
    assert len(recording.messages) + len(recording.views) == len(messages)


async def test_every_message_fits_its_schema_in_specs(
    autojump_clock: MockClock, session_file: Path
) -> None:
    recording = read_recording(session_file)
    schemas = {
        kind: json.loads((SPEC_SCHEMAS / f"record-{kind.replace('_', '-')}.json").read_text())
        for kind in ("command", "targets", "joint_states", "state", "fault", "peer")
    }
    for message in recording.messages:
        jsonschema.validate(message.data, schemas[message.kind])
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate({"t": "soon"}, schemas["targets"])


async def test_the_recording_tells_the_story(autojump_clock: MockClock, session_file: Path) -> None:
    recording = read_recording(session_file)
    summary = summarize(recording)
    assert [e["reason"] for e in summary["estops"]] == ["test stop"]
    assert summary["refused_commands"] == 1
    assert summary["robots"]["arm"]["robot_type"] == "so-arm100"
    errors = summary["robots"]["arm"]["tracking_error_deg"]
    assert set(errors) == {"Rotation", "Pitch", "Elbow", "Wrist_Pitch", "Wrist_Roll", "Jaw"}
    lines = timeline(recording, robot="arm")
    assert any("estopped" in line and "test stop" in line for line in lines)
    assert any("refused ESTOPPED" in line for line in lines)
    rows = export(recording, "csv", "/robots/arm/targets").splitlines()
    assert rows[0].startswith("topic,log_time,t,joint.Rotation")
    assert len(rows) - 1 == sum(1 for m in recording.messages if m.kind == "targets")
    lines_jsonl = export(recording, "jsonl").splitlines()
    assert len(lines_jsonl) == len(recording.messages)


async def test_a_replayed_session_behaves_the_same(
    autojump_clock: MockClock, session_file: Path
) -> None:
    original = read_recording(session_file)
    replayed = await replay_session(original, "arm")
    expected, actual = behaviour(original, "arm"), behaviour(replayed, "arm")
    assert len(expected) > 100
    assert [e[1] for e in expected].count("command") == 6
    assert actual == expected


async def test_replay_master_timing_speed_and_window(
    autojump_clock: MockClock, session_file: Path, manager: RobotManager
) -> None:
    commands = recorded_commands(read_recording(session_file), "arm")
    assert commands[0].at == 0.0
    robot = await manager.create_robot("so-arm100", robot_id="copy")
    received: list[float] = []
    with robot.subscribe(maxlen=10_000) as events:
        start = trio.current_time()
        await robot.attach_master(ReplayMaster(commands, speed=2.0))
        await trio.sleep(commands[-1].at)
        for event in events.drain():
            if type(event).__name__ == "CommandHandled":
                received.append(round(event.time - start, 9))  # type: ignore[union-attr]
    assert received == [round(c.at / 2.0, 9) for c in commands]
    window = recorded_commands(read_recording(session_file), "arm", start=1.5, end=4.0)
    assert window and all(0 <= c.at < 2.5 for c in window)
    assert len(window) < len(commands)


async def test_replay_is_refused_during_estop_and_stopped_by_one(
    autojump_clock: MockClock, session_file: Path, manager: RobotManager
) -> None:
    commands = recorded_commands(read_recording(session_file), "arm")
    robot = await manager.create_robot("so-arm100", robot_id="copy")
    recorder = RecordingSlave()
    await robot.attach_slave(recorder)
    await robot.estop("before")
    with pytest.raises(ArenaError) as info:
        await robot.attach_master(ReplayMaster(commands))
    assert info.value.code is ErrorCode.ESTOPPED
    await robot.reset()
    master = ReplayMaster(commands, loop=True)
    await robot.attach_master(master)
    await trio.sleep(1.5)
    await robot.estop("during")
    stopped_at = trio.current_time()
    await robot.reset()
    await trio.sleep(30)
    assert robot.snapshot().master is None and robot.snapshot().mode is Mode.IDLE
    assert all(t <= stopped_at for t, _ in recorder.targets)


def test_bad_files_give_a_clear_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    not_mcap = tmp_path / "notes.mcap"
    not_mcap.write_text("hello")
    empty = tmp_path / "empty.mcap"
    empty.write_bytes(b"")
    for path in (not_mcap, empty, tmp_path / "missing.mcap"):
        with pytest.raises(ArenaError) as info:
            read_recording(path)
        assert info.value.code is ErrorCode.INVALID_RECORDING
        assert cli.main(["inspect", str(path)]) == 2
        assert "arena inspect:" in capsys.readouterr().err


def test_foreign_mcap_files_are_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from mcap.writer import Writer

    path = tmp_path / "foreign.mcap"
    with open(path, "wb") as stream:
        writer = Writer(stream)
        writer.start()
        schema = writer.register_schema("x", "jsonschema", b"{}")
        channel = writer.register_channel("/camera/image", "json", schema)
        writer.add_message(channel, 1, b"{}", 1)
        writer.finish()
    assert cli.main(["inspect", str(path)]) == 2
    assert "no Arena" in capsys.readouterr().err


def test_truncated_files_are_read_and_recovered(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    complete = trio.run(record_session, tmp_path, clock=MockClock(autojump_threshold=0))
    whole = read_recording(complete)
    data = complete.read_bytes()
    with open(complete, "rb") as stream:
        summary = make_reader(stream).get_summary()
    assert summary is not None
    # cut in the middle of a chunk two thirds of the way in (the first holds the 3D model)
    chunks = sorted(summary.chunk_indexes, key=lambda index: index.chunk_start_offset)
    middle = chunks[len(chunks) * 2 // 3]
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: middle.chunk_start_offset + middle.chunk_length // 2])
    partial = read_recording(cut)
    assert partial.truncated and 0 < len(partial.messages) < len(whole.messages)
    assert partial.messages == whole.messages[: len(partial.messages)]
    for command in (
        ["inspect", str(cut)],
        ["timeline", str(cut)],
        ["export", str(cut), "--format", "csv"],
    ):
        assert cli.main(command) == 0
        assert "truncated" in capsys.readouterr().err
    assert cli.main(["recover", str(cut), "-o", str(tmp_path / "fixed.mcap")]) == 0
    with open(tmp_path / "fixed.mcap", "rb") as stream:
        fixed = list(make_reader(stream).iter_messages())
    assert len(fixed) == len(partial.messages) + len(partial.views)
    assert partial.views and write_recording(partial, tmp_path / "again.mcap") == len(fixed)


def test_recording_names_cannot_escape_the_folder(tmp_path: Path) -> None:
    assert check_name(tmp_path, "a.mcap") == (tmp_path / "a.mcap").resolve()
    for name in ("../a.mcap", "/etc/passwd", "a/b.mcap", ".hidden.mcap", "a.txt", "", "..\\a.mcap"):
        with pytest.raises(ArenaError) as info:
            check_name(tmp_path, name)
        assert info.value.code is ErrorCode.UNKNOWN_RECORDING


SERVE_DEMO = (sys.executable, "-m", "arena.cli", "serve", "--demo", "--port", "0")


@contextlib.asynccontextmanager
async def killable_server(folder: Path) -> AsyncIterator[tuple[trio.Process, int]]:
    """A real `arena serve --demo` process recording into `folder`, its sequence master
    looping for two seconds: yields (server process, pid of its MCAP writer process)."""
    process = await trio.lowlevel.open_process(
        [*SERVE_DEMO, "--recordings-dir", str(folder)],
        stderr=-1,
        env={**os.environ, "LOG_LEVEL": "INFO"},
    )
    try:
        assert process.stderr is not None
        text = b""
        with trio.fail_after(30):
            while (found := re.search(rb"listening on (http://\S+)", text)) is None:
                chunk = await process.stderr.receive_some()
                assert chunk, text.decode()
                text += chunk
        async with httpx.AsyncClient(base_url=found.group(1).decode()) as http:
            await http.post(
                "/api/robots/demo-arm/master", json={"type": "mock-sequence", "loop": True}
            )
            await trio.sleep(2.0)
        # Started from a worker thread, so listed under that thread's task.
        tasks = Path(f"/proc/{process.pid}/task").glob("*/children")
        children = [pid for task in tasks for pid in task.read_text().split()]
        (writer,) = [
            int(pid)
            for pid in children
            if b"writer_process" in Path(f"/proc/{pid}/cmdline").read_bytes()
        ]
        yield process, writer
    finally:
        with contextlib.suppress(ProcessLookupError):
            process.kill()
        await process.wait()


async def test_a_killed_server_still_leaves_a_complete_file(tmp_path: Path) -> None:
    """SIGKILL to the server: its writer process sees the pipe close and finishes the file."""
    folder = tmp_path / "rec"
    async with killable_server(folder) as (server, writer):
        killed_at = time.time()
        server.send_signal(signal.SIGKILL)
    with trio.fail_after(10):
        while Path(f"/proc/{writer}").exists():
            await trio.sleep(0.05)
    (path,) = folder.glob("*.mcap")
    recording = read_recording(path)
    assert not recording.truncated
    assert killed_at - max(m.log_time for m in recording.messages) / 1e9 < 1.0
    assert any(m.kind == "command" for m in recording.messages)


async def test_losing_both_processes_loses_at_most_the_last_flush(tmp_path: Path) -> None:
    """SIGKILL to the server and its writer at once (a power cut): the file reads and
    recovers, and no more than the last flush interval is missing."""
    folder = tmp_path / "rec"
    async with killable_server(folder) as (server, writer):
        killed_at = time.time()
        os.kill(writer, signal.SIGKILL)
        server.send_signal(signal.SIGKILL)
    (path,) = folder.glob("*.mcap")
    recording = read_recording(path)
    assert recording.truncated
    assert killed_at - max(m.log_time for m in recording.messages) / 1e9 < 1.0
    assert any(m.kind == "command" for m in recording.messages)
    fixed = tmp_path / "fixed.mcap"
    assert cli.main(["recover", str(path), "-o", str(fixed)]) == 0
    with open(fixed, "rb") as stream:
        written = len(list(make_reader(stream).iter_messages()))
    assert written == len(recording.messages) + len(recording.views)


def test_plot_draws_every_joint(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    golden = Path(__file__).resolve().parent.parent / "recordings" / "golden"
    output = tmp_path / "wave.png"
    assert cli.main(["plot", str(golden / "manual-estop-reset.mcap"), "-o", str(output)]) == 0
    assert output.read_bytes().startswith(b"\x89PNG") and output.stat().st_size > 10_000


def test_files_rotate_by_size_and_each_stands_alone(tmp_path: Path) -> None:
    # The writer process rotates between batches, once a file has passed max_bytes.
    golden = read_recording(GOLDEN / "gentle-wave.mcap")
    items = [(m.robot_id, m.kind, json.dumps(m.data).encode(), m.log_time) for m in golden.messages]
    writer = McapWriterProcess(
        FileSeries(tmp_path, {"test": "rotation"}, max_bytes=1)
    )  # every batch fills one
    writer.robots["arm"] = {"robot_type": "so-arm100", "name": "arm", "urdf": "<robot/>"}
    whole = min(500, len(items) // 100 * 100)
    assert whole >= 300  # (the demo's file holds several hundred messages)
    batches = [items[i : i + 100] for i in range(0, whole, 100)]
    try:
        for batch in batches:
            writer.write(batch)
    finally:
        writer.shutdown()
    # each file brings the robot's 3D model along (one scene message)
    assert len(writer.files) == len(batches) and writer.messages == whole + len(batches)
    for path, batch in zip(writer.files, batches, strict=True):
        with open(path, "rb") as stream:
            reader = make_reader(stream)
            topics = [channel.topic for _, channel, _ in reader.iter_messages()]
            assert len(topics) == len(batch) + 1 and topics.count("/robots/arm/scene") == 1
            assert {"arena", "robot/arm"} <= {m.name for m in reader.iter_metadata()}
        assert [m.log_time for m in read_recording(path).messages] == [i[3] for i in batch]


def test_after_the_writer_process_dies_the_next_batch_starts_a_new_one(tmp_path: Path) -> None:
    golden = read_recording(GOLDEN / "gentle-wave.mcap")
    items = [(m.robot_id, m.kind, json.dumps(m.data).encode(), m.log_time) for m in golden.messages]
    writer = McapWriterProcess(FileSeries(tmp_path, {"test": "restart"}))
    writer.shutdown()  # nothing started yet: nothing to do
    try:
        writer.write(items[:50])
        first = writer.path
        assert first is not None and writer.messages == 50
        child = writer._process
        assert child is not None
        os.kill(child.pid, signal.SIGKILL)
        child.wait()
        writer.write(items[50:100])
        assert writer.path not in (None, first) and writer._process is not child
        assert writer.messages == 100 and writer.files == [first, writer.path]
    finally:
        writer.shutdown()
    # The first file was cut where the child died, after its last flush: nothing is missing.
    cut, second = read_recording(first), read_recording(writer.files[-1])
    assert cut.truncated and not second.truncated
    log_times = [m.log_time for m in cut.messages + second.messages]
    assert log_times == [i[3] for i in items[:100]]


def test_a_writer_process_that_fails_mid_batch_is_reported_as_an_io_error(tmp_path: Path) -> None:
    # A record of a kind with no schema crashes the child (a bug, not a disk error): the
    # batch fails with OSError, which the recorder counts as dropped, and the next one works.
    writer = McapWriterProcess(FileSeries(tmp_path, {"test": "crash"}))
    good = [("arm", "state", b"{}", 1)]
    try:
        with pytest.raises(OSError, match="recording process failed"):
            writer.write([("arm", "no-such-kind", b"{}", 1)])
        assert writer.path is None and writer._process is None
        writer.write(good)
        assert writer.messages == 1 and writer.path is not None
    finally:
        writer.shutdown()


async def test_a_replay_behind_schedule_keeps_order_and_yields_to_an_estop(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    # Every command is due at once: the fast path (decided in the replay's own task while the
    # robot is idle) must keep them in order, let other tasks run, and stop on an e-stop.
    robot = await manager.create_robot(
        "so-arm100",
        robot_id="burst",
        policy=dataclasses.replace(
            load_robot_model("so-arm100").safety, command_rate=1e9, command_burst=10**9
        ),
    )
    slave = RecordingSlave()
    await robot.attach_slave(slave)
    values = [round(0.01 * i, 2) for i in range(1, 2001)]
    burst = [TimedCommand(0.0, Command.of({"Rotation": v})) for v in values]
    handled: list[tuple[float, bool]] = []
    stopped_after: list[int] = []
    with robot.subscribe(maxlen=100_000) as events:

        async def estop_midway() -> None:
            async for event in events:
                if isinstance(event, CommandHandled):
                    handled.append((event.command.joints[0].value, event.result.accepted))
                    if len(handled) == 300:
                        stopped_after.append(len(handled))
                        await robot.estop("midway")
                elif isinstance(event, StateChanged) and event.mode is Mode.ESTOPPED:
                    return

        master = ReplayMaster(burst, speed=1000.0)
        async with trio.open_nursery() as nursery:
            nursery.start_soon(estop_midway)
            await robot.attach_master(master)
        await trio.sleep(1.0)
    accepted = [value for value, ok in handled if ok]
    # The watcher ran while the replay was still going (the replay yields), so the e-stop cut
    # it short: it detaches the master, and a command already on its way when it struck is
    # refused (trio runs ready tasks in either order). What was accepted came in recorded order.
    assert stopped_after == [300]
    assert 300 <= len(accepted) < len(values)
    assert accepted == values[: len(accepted)]
    refused = handled[len(accepted) :]
    assert handled[: len(accepted)] == [(value, True) for value in accepted]
    assert len(refused) <= 1 and master.refused <= 1
    assert robot.snapshot().mode is Mode.ESTOPPED and robot.snapshot().master is None
    assert slave.targets and all(
        target["Rotation"] <= accepted[-1] + 1e-9 for _, target in slave.targets
    )


async def test_the_recorder_counts_overflow_and_writes_robots_in_time_order(
    autojump_clock: MockClock, tmp_path: Path
) -> None:
    # Queues are drained once per batch: a queue shorter than a burst loses its oldest.
    recorder = Recorder(tmp_path, flush_interval=1.0, batch_interval=1.0, queue_size=20)
    async with trio.open_nursery() as nursery:
        await nursery.start(recorder.run)
        async with open_manager() as manager:
            manager.on_create.append(recorder.follow)
            robots = [await manager.create_robot("so-arm100", robot_id=n) for n in ("a", "b")]
            for robot in robots:
                await robot.estop("hold still")  # refused commands: one event each
            await trio.sleep(1.5)  # a flush between: the set-up is written whole
            assert recorder.dropped == 0
            for n in range(30):  # inside one flush interval, the robots interleaved in time
                for robot in robots:
                    await robot.command(Command.of({"Rotation": float(n)}))
                    await trio.sleep(0.001)
            await trio.sleep(1.0)
            assert recorder.dropped == 2 * 10
            await manager.delete("b")
            await trio.sleep(1.0)
            assert recorder.dropped == 2 * 10, "a deleted robot's losses still count"
        nursery.cancel_scope.cancel()
    (path,) = recorder.writer.files
    with open(path, "rb") as stream:
        in_file_order = list(make_reader(stream).iter_messages(log_time_order=False))
    log_times = [message.log_time for _, _, message in in_file_order]
    assert log_times == sorted(log_times)
    refused = [
        (channel.topic, json.loads(message.data)["joints"][0]["value"])
        for _, channel, message in in_file_order
        if channel.topic.endswith("/command")
    ]
    assert refused == [(f"/robots/{r}/command", float(n)) for n in range(10, 30) for r in "ab"]


async def test_a_stop_during_a_batch_in_flight_keeps_that_batch_in_the_stopped_file(
    tmp_path: Path,
) -> None:
    # The periodic batch has drained the queues and its thread is on its way to the writer
    # when `stop` comes: the stopped file must still hold what happened before the stop.
    recorder = Recorder(tmp_path, flush_interval=0.05, batch_interval=0.05)
    in_flight = threading.Event()
    go_on = threading.Event()
    write_events = recorder.writer.write_events

    def held(slices: list[bytes], *, flush: bool = True) -> None:
        if slices:  # the batch with the command: wait here, before the writer's lock
            in_flight.set()
            go_on.wait(30)
        write_events(slices, flush=flush)

    async with trio.open_nursery() as nursery:
        await nursery.start(recorder.run)
        async with open_manager() as manager:
            manager.on_create.append(recorder.follow)
            robot = await manager.create_robot("so-arm100", robot_id="arm")
            recorder.writer.write_events = held  # type: ignore[method-assign]
            await robot.command(Command.of({"Rotation": 5.0}))
            await trio.to_thread.run_sync(in_flight.wait, 30)
            async with trio.open_nursery() as stopping:
                stopped: list[dict[Path, str]] = []

                async def stop() -> None:
                    stopped.append(await recorder.stop())

                stopping.start_soon(stop)
                # Until the stop waits behind the batch in flight (or, if it does not wait,
                # has closed the file already): only then may the batch go on.
                writing = recorder._writing
                await eventually(
                    lambda: bool(stopped) or writing.statistics().tasks_waiting > 0,
                    what="the stop, waiting or done",
                )
                go_on.set()
        nursery.cancel_scope.cancel()
    ((path,),) = stopped
    commands = [m.data for m in read_recording(path).messages if m.kind == "command"]
    assert [c["joints"][0]["value"] for c in commands] == [5.0]


async def test_records_reach_the_disk_within_a_flush_interval_when_the_robot_goes_quiet(
    tmp_path: Path,
) -> None:
    # Real time: the batches cross a thread and a process. Batches between flushes stay in
    # the open chunk; the next flush writes them even if nothing else happens. What is on disk
    # is checked right after each hand-over returns (in the recorder's thread), and the
    # recorder's own clock says when each flush was decided: nothing depends on how fast the
    # test itself runs.
    recorder = Recorder(tmp_path, flush_interval=0.5, batch_interval=0.05)
    handed: list[tuple[float, bool, int]] = []  # (trio time, flush, commands on disk after)
    write_events = recorder.writer.write_events

    def commands_on_disk() -> int:
        files = list(tmp_path.glob("*.mcap"))
        try:
            return sum(m.kind == "command" for m in read_recording(files[0]).messages)
        except (IndexError, ArenaError):  # no file yet, or not even its magic on disk
            return 0

    def watched(slices: list[bytes], *, flush: bool = True, at: float = 0.0) -> None:
        write_events(slices, flush=flush)
        handed.append((at, flush, commands_on_disk()))

    async def write(batch: Any, flush: bool = True) -> None:
        original = recorder.writer.write_events
        recorder.writer.write_events = partial(watched, at=trio.current_time())  # type: ignore[method-assign]
        try:
            await real_write(batch, flush)
        finally:
            recorder.writer.write_events = original  # type: ignore[method-assign]

    real_write = recorder._write
    recorder._write = write  # type: ignore[method-assign]

    async with trio.open_nursery() as nursery:
        await nursery.start(recorder.run)
        async with open_manager() as manager:
            manager.on_create.append(recorder.follow)
            robot = await manager.create_robot("so-arm100", robot_id="quiet")
            await robot.command(Command.of({"Rotation": 0.01}))
            await eventually(lambda: any(on_disk == 1 for _, _, on_disk in handed))
            first = len(handed)
            await robot.command(Command.of({"Rotation": 0.02}))
            await eventually(lambda: any(on_disk == 2 for _, _, on_disk in handed))
        nursery.cancel_scope.cancel()
    # The batch holding the first command was flushed at once (the first flush is due).
    flushed_first = next(i for i, (_, _, on_disk) in enumerate(handed) if on_disk == 1)
    assert handed[flushed_first][1]
    # The second command went out in a batch that was not flushed, and stayed in the open
    # chunk until the next flush, a flush interval after the one before.
    after = handed[first:]
    done = next(i for i, (_, _, on_disk) in enumerate(after) if on_disk == 2)
    assert all(not flush and on_disk == 1 for _, flush, on_disk in after[:done])
    assert after[done][1]
    flushes = [at for at, flush, _ in handed if flush]
    assert after[done][0] - flushes[flushes.index(after[done][0]) - 1] >= 0.5 - 1e-9


def test_the_chunked_writer_makes_files_mcaps_own_readers_read_whole(tmp_path: Path) -> None:
    path = tmp_path / "w.mcap"
    sent: list[tuple[str, int, bytes]] = []
    with open(path, "wb") as stream:
        writer = ChunkedWriter(stream, chunk_size=2048)  # many chunks
        writer.start(profile="arena", library="test")
        writer.add_metadata("arena", {"server": "test"})
        schema = writer.register_schema("targets", "jsonschema", b'{"type": "object"}')
        topics = ["/robots/a/targets", "/robots/b/targets"]
        channels = [writer.register_channel(t, "json", schema) for t in topics]
        for n in range(500):
            # Times out of order inside a chunk too (the recorder sorts; a writer must not care).
            log_time = 1_000_000_000 + n * 1000 + (500 if n % 3 == 0 else 0)
            data = json.dumps({"t": n, "joints": {"Rotation": n * 0.5}}).encode()
            writer.add_message(channels[n % 2], log_time, data)
            sent.append((topics[n % 2], log_time, data))
        writer.finish()
    with open(path, "rb") as stream:
        reader = make_reader(stream, validate_crcs=True)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        statistics = summary.statistics
        assert statistics.message_count == 500 and statistics.chunk_count > 5
        assert statistics.channel_message_counts == {channels[0]: 250, channels[1]: 250}
        assert statistics.message_start_time == min(t for _, t, _ in sent)
        assert statistics.message_end_time == max(t for _, t, _ in sent)
        read = [(c.topic, m.log_time, m.data) for _, c, m in reader.iter_messages()]
        assert read == sorted(sent, key=lambda item: item[1])
        assert [m.metadata for m in reader.iter_metadata()] == [{"server": "test"}]
    with open(path, "rb") as stream:
        streamed = NonSeekingReader(stream, validate_crcs=True).iter_messages(log_time_order=False)
        assert [(c.topic, m.log_time, m.data) for _, c, m in streamed] == sent
    # Cut mid-file: every complete chunk still reads, and the file shows as cut.
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    recording = read_recording(cut)
    assert recording.truncated and 100 < len(recording.messages) < 500
    assert [m.log_time for m in recording.messages] == [t for _, t, _ in sent][
        : len(recording.messages)
    ]


def test_events_packed_for_the_writer_process_become_the_same_records() -> None:
    # The server packs robot events as they are; the writer process makes the records. Every
    # kind, with the awkward fields (enums, None, tuples of clamps, speeds), must survive.
    command = Command((JointGoal("Rotation", 10.0, 30.0), JointGoal("Jaw", 900.0)), 0.5, "ui")
    events: list[RobotEvent] = [
        CommandHandled(
            "a",
            "m1",
            command,
            CommandResult(True, None, "clamped", (Clamp("Jaw", 900.0, 100.0),)),
            1.5,
            2.0,
        ),
        CommandHandled(
            "a", "m2", command, CommandResult.refused(ErrorCode.ESTOPPED, "no"), 1.6, 2.1
        ),
        TargetsSent("a", {"Rotation": 1.25, "Jaw": -3.0}, 1.7, 2.2),
        JointStatesReceived("b", "s1", {"Rotation": 1.0}, 1.8, 2.3),
        StateChanged("a", Mode.ESTOPPED, None, "stop", "button", 1.9, 2.4),
        FaultReported("b", "s1", "OVERHEAT", "hot", Severity.CRITICAL, "Elbow", 2.0, 2.5),
        PeerChanged("a", "master", "m1", "websocket", "detached", "left", 2.1, 2.6, True),
    ]
    # Slices of two robots whose clocks differ by a second: the child writes all of them in
    # time order, across the slices.
    slices = [pack_events("a", 1000.0, events[:3]), pack_events("b", 999.0, events[3:])]
    items = items_of_events(slices)
    expected = sorted(
        (
            (robot_id, record_of(e)[0], msgspec.json.encode(record_of(e)[1]), log_time)
            for robot_id, offset, part in (("a", 1000.0, events[:3]), ("b", 999.0, events[3:]))
            for e in part
            for log_time in [int((e.time + offset) * 1e9)]
        ),
        key=lambda item: item[3],
    )
    assert items == expected
    assert [item[0] for item in items] == ["b"] * 4 + ["a"] * 3  # b's clock runs a second behind


def test_the_recorders_retries_back_off_from_one_second_to_thirty() -> None:
    retry = Backoff(1.0, 30.0)
    assert retry.ready(0.0)
    attempts = []
    now = 0.0
    while now < 120.0:  # a full disk for two minutes, the recorder asking every 50 ms
        if retry.ready(now):
            attempts.append(now)
            retry.failed(now)
        now = round(now + 0.05, 2)
    gaps = [round(b - a, 2) for a, b in itertools.pairwise(attempts)]
    assert gaps == [1.0, 2.0, 4.0, 8.0, 16.0, 30.0, 30.0]  # 7 attempts, not 2,400
    assert retry.wait(now) > 0
    retry.succeeded()  # the disk is back (or the operator starts recording again)
    assert retry.ready(now) and retry.wait(now) == 0.0


def test_a_full_disk_leaves_no_empty_file_behind(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Every file's writes fail once a few bytes are in (ENOSPC): the files the writer opens
    # while the disk is full hold nothing, and are removed; one that holds flushed messages
    # stays, cut where the disk filled, and reads back.
    room = {"bytes": 1 << 20}

    class FullDisk(io.FileIO):
        def write(self, data: Any) -> int:
            if len(data) > room["bytes"]:
                raise OSError(errno.ENOSPC, "No space left on device")
            room["bytes"] -= len(data)
            return super().write(data)

    def opener(path: Path, mode: str) -> IO[bytes]:
        return FullDisk(path, "w") if "w" in mode else open(path, mode)

    monkeypatch.setattr(mcap_file, "open", opener, raising=False)
    writer = mcap_file.McapFileWriter(FileSeries(tmp_path, {"test": "full"}))
    state = json.dumps({"robot_id": "arm", "mode": "idle"}).encode()
    writer.write([("arm", "state", state, 1)])  # flushed while there was room
    kept = writer.path
    room["bytes"] = 0  # the disk fills
    for attempt in range(20):
        with pytest.raises(OSError):
            writer.write([("arm", "state", state, 2 + attempt)])
    assert kept is not None
    assert [p.name for p in tmp_path.iterdir()] == [kept.name]
    assert read_recording(kept).messages


async def test_a_robot_deleted_mid_episode_cuts_it_and_the_recording_lists_it_so(
    server: RunningServer,
) -> None:
    async with server.client() as http:
        assert (await http.post("/api/robots", json={"id": "arm"})).status_code == 201
        started = await http.post("/api/robots/arm/episodes/start", json={"task": "stack"})
        assert started.status_code == 201
        assert (await http.delete("/api/robots/arm")).status_code == 200
        name = (await http.post("/api/recordings/current/stop")).json()["stopped"]
        summary = (await http.get(f"/api/recordings/{name}")).json()
    (episode,) = summary["episodes"]
    assert (episode["robot"], episode["index"], episode["task"]) == ("arm", 0, "stack")
    assert episode["ended"] == "cut" and episode["seconds"] >= 0
