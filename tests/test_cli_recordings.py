"""The recording commands as a newcomer meets them: `arena inspect`, `timeline`, `plot`,
`recover` and friends on real files, through `arena.cli.main` or a real process."""

from __future__ import annotations

import json
import os
import re
import signal
import socket
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
import trio
from mcap.reader import make_reader
from trio.testing import MockClock

from arena import cli
from arena.recording.mcap_file import FileSeries, McapFileWriter, read_recording
from arena.recording.writer_process import McapWriterProcess
from tests.conftest import need
from tests.test_recording import GOLDEN, record_session

ROOT = Path(__file__).resolve().parent.parent
#: The `arena` command as a process, without `python -m arena` (so that it runs on any tree).
ARENA = (sys.executable, "-c", "import sys; from arena.cli import main; sys.exit(main())")
SECOND = 1_000_000_000


def run(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    """`arena ARGV` in this process: (exit status, stdout, stderr)."""
    status = cli.main(argv)
    out, err = capsys.readouterr()
    return status, out, err


@pytest.fixture(scope="module")
def session_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A recorded session (manual commands, a sequence, an e-stop, a clamped command) with
    Foxglove's view, made by the real recorder on virtual time."""
    folder = tmp_path_factory.mktemp("session")
    return trio.run(record_session, folder, clock=MockClock(autojump_threshold=0))


def write_records(folder: Path, records: list[tuple[str, str, dict[str, Any], int]]) -> Path:
    """A complete recording of `records` (robot, kind, record, log time), written by the
    recorder's own file writer."""
    writer = McapFileWriter(FileSeries(folder, {"test": "records"}))
    writer.write(
        [(robot, kind, json.dumps(data).encode(), at) for robot, kind, data, at in records]
    )
    path = writer.path
    writer.close()
    assert path is not None
    return path


# -- inspect: in progress, gaps, counts --------------------------------------------------------


def test_inspect_calls_a_file_being_written_in_progress_and_a_cut_one_truncated(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    golden = read_recording(GOLDEN / "gentle-wave.mcap")
    items = [(m.robot_id, m.kind, json.dumps(m.data).encode(), m.log_time) for m in golden.messages]
    writer = McapWriterProcess(FileSeries(tmp_path, {"test": "in progress"}))
    try:
        writer.write(items[:200])  # flushed: on disk, the file still open in the writer
        assert writer.path is not None
        path = writer.path
        status, out, err = run(["inspect", str(path)], capsys)
        assert status == 0
        assert "truncated" not in out + err
        assert out.splitlines()[0].endswith("(in progress: still being written)")
        assert "is in progress (still being written)" in err
        assert read_recording(path).in_progress
        child = writer._process
        assert child is not None
        os.kill(child.pid, signal.SIGKILL)  # the writer dies: the file stays cut
        child.wait()
    finally:
        writer.shutdown()
    status, out, err = run(["inspect", str(path)], capsys)
    assert "in progress" not in out + err
    assert out.splitlines()[0].endswith("(truncated: its writer stopped before the end)")
    assert "is truncated" in err and "arena recover" in err


def test_inspect_counts_only_real_gaps_and_summarises_them(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Five minutes with long idle stretches (every topic silent) and one real gap: targets
    kept going for 3 s and the slave answered none of them."""
    start = 1_700_000_000 * SECOND
    records: list[tuple[str, str, dict[str, Any], int]] = []

    def at(seconds: float) -> int:
        return start + int(seconds * SECOND)

    def peer(seconds: float, change: str, slave: str = "s1") -> None:
        data = {"t": seconds, "role": "slave", "peer_id": slave, "kind": "mock-slave"}
        records.append(("arm", "peer", {**data, "change": change, "reason": ""}, at(seconds)))

    def burst(begin: float, seconds: float, answered: bool) -> None:
        for step in range(int(seconds * 50)):
            t = begin + step / 50
            joints = {"Rotation": float(step)}
            records.append(("arm", "targets", {"t": t, "joints": joints}, at(t)))
            if answered:
                data = {"t": t + 0.01, "slave_id": "s1", "joints": joints}
                records.append(("arm", "joint_states", data, at(t + 0.01)))

    peer(0.0, "attached")
    peer(0.0, "attached", "display")  # a slave that shows targets and never reports
    for begin in (1.0, 70.0, 150.0, 230.0):  # moves, each followed by a minute at rest
        burst(begin, 2.0, answered=True)
    burst(290.0, 3.0, answered=False)  # the slave went quiet while the arm was driven
    burst(293.0, 1.0, answered=True)
    peer(300.0, "detached")
    burst(301.0, 5.0, answered=False)  # no slave: nothing to answer
    records.append(("arm", "audit", {"t": 1.0, "user": "ann", "action": "x", "detail": ""}, at(1)))
    path = write_records(tmp_path, records)

    status, out, _ = run(["inspect", str(path)], capsys)
    assert status == 0
    # A topic of one message has no rate, and says none.
    (audit,) = [
        line.split() for line in out.splitlines() if line.startswith("topic") and "audit" in line
    ]
    assert audit[2:] == ["1", "msgs"]
    assert all(
        line.endswith(" Hz")
        for line in out.splitlines()
        if line.startswith("topic") and "audit" not in line
    )
    gap_lines = [line for line in out.splitlines() if "gap" in line]
    assert gap_lines[0] == "gaps       1 (a slave left targets unanswered for over 1 s)"
    assert gap_lines[1].split() == [
        "gap",
        "robot=arm",
        "slave=s1",
        "from_s=290.0",
        "seconds=3.01",
        "until=joint",
        "state",
    ]
    assert len(gap_lines) == 2
    status, out, _ = run(["inspect", str(path), "--json"], capsys)
    assert [gap["seconds"] for gap in json.loads(out)["gaps"]] == [3.01]


def test_inspect_lists_a_few_of_many_entries_and_counts_the_rest(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    start = 1_700_000_000 * SECOND
    faults = [
        (
            "arm",
            "fault",
            {
                "t": float(i),
                "peer_id": "s1",
                "code": "SIMULATED_FAULT",
                "message": "injected",
                "severity": "warning",
                "joint": None,
            },
            start + i * SECOND,
        )
        for i in range(40)
    ]
    path = write_records(tmp_path, faults)
    status, out, _ = run(["inspect", str(path)], capsys)
    assert status == 0
    lines = out.splitlines()
    assert "faults     40" in lines
    assert sum(line.startswith("  fault ") for line in lines) == cli.LISTED
    assert f"  ... and {40 - cli.LISTED} more (--json lists every one)" in lines
    status, out, _ = run(["inspect", str(path), "--json"], capsys)
    assert len(json.loads(out)["faults"]) == 40


def test_inspect_counts_what_recover_writes(
    session_file: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    status, out, _ = run(["inspect", str(session_file), "--json"], capsys)
    summary = json.loads(out)
    assert summary["view_messages"] > 0  # the session has Foxglove's view too
    fixed = tmp_path / "fixed.mcap"
    status, out, _ = run(["recover", str(session_file), "-o", str(fixed)], capsys)
    assert status == 0
    with open(fixed, "rb") as stream:
        written = sum(1 for _ in make_reader(stream).iter_messages())
    assert summary["messages"] == written == int(out.split()[1])
    assert summary["messages"] == summary["arena_messages"] + summary["view_messages"]
    assert sum(topic["count"] for topic in summary["topics"].values()) == written
    status, out, _ = run(["inspect", str(session_file)], capsys)
    assert f"messages   {written} (" in out


# -- timeline: the clamp as recorded -----------------------------------------------------------


def test_timeline_shows_a_clamped_command_as_clamped(
    session_file: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    recording = read_recording(session_file)
    (clamped,) = [m for m in recording.messages if m.kind == "command" and m.data["clamped"]]
    (clamp,) = clamped.data["clamped"]
    status, out, _ = run(["timeline", str(session_file), "--robot", "arm"], capsys)
    assert status == 0
    (line,) = [line for line in out.splitlines() if "Jaw=500" in line]
    expected = f"clamped Jaw {clamp['requested']:g} -> {clamp['applied']:g}"
    assert line.endswith(f"-> {expected}") and "accepted" not in line


def test_timeline_says_so_when_its_window_holds_nothing(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """`--from`/`--to` past the robot's records printed nothing at all, as if the file were
    empty; a note says where its records are (exit 0: an empty window is no error)."""
    golden = str(GOLDEN / "gentle-wave.mcap")
    status, out, err = run(["timeline", golden, "--robot", "arm", "--from", "100"], capsys)
    assert status == 0 and out.strip() == ""
    assert err.startswith("note: no record of robot 'arm' from 100 s to the end; ")
    assert "its records span 0.000-6.5" in err, err
    status, out, err = run(["timeline", golden, "--from", "1", "--to", "2"], capsys)
    assert status == 0 and out.strip() and not err  # a window with records: no note


# -- errors name the flag ----------------------------------------------------------------------


@pytest.fixture
def two_robots(tmp_path: Path) -> Path:
    start = 1_700_000_000 * SECOND
    records = [
        (robot, "targets", {"t": 0.0, "joints": {"Rotation": 1.0}}, start + i)
        for i, robot in enumerate(("left", "right"))
    ]
    return write_records(tmp_path, records)


@pytest.mark.parametrize(
    ("argv", "flag"),
    [
        (["plot", "{file}", "-o", "{tmp}/x.png"], "--robot"),
        (["replay", "{file}", "--to", "ws://127.0.0.1:9/ws/master/x"], "--robot"),
        (
            ["export", "{file}", "--format", "lerobot", "--robot", "nobody", "-o", "{tmp}/d"],
            "--robot",
        ),
        (["timeline", "{file}", "--robot", "nobody"], "--robot"),
        (["plot", "{file}", "--robot", "nobody", "-o", "{tmp}/x.png"], "--robot"),
        (["export", "{file}", "--topic", "/robots/left/nothing"], "--topic"),
        (["replay", "{golden}", "--speed", "0", "--to", "ws://127.0.0.1:9/x"], "--speed"),
        (["estop-test", "--robot", "arm"], "--url"),
        (["estop-test", "--url", "http://127.0.0.1:{closed}", "--robot", "arm"], "--url"),
        (["replay", "{golden}", "--to", "ws://127.0.0.1:{closed}/ws/master/arm"], "--to"),
    ],
)
def test_command_line_errors_name_the_flag(
    argv: list[str],
    flag: str,
    two_robots: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    if "lerobot" in argv:
        need("lerobot", "lerobot")  # asked for first: without it, the refusal is that
    golden = GOLDEN / "gentle-wave.mcap"
    with socket.socket() as probe:  # a port nothing listens on
        probe.bind(("127.0.0.1", 0))
        closed = probe.getsockname()[1]
    args = [a.format(file=two_robots, tmp=tmp_path, golden=golden, closed=closed) for a in argv]
    status, _, err = run(args, capsys)
    assert status == 2
    assert err.count("\n") == 1 and err.startswith(f"arena {args[0]}: "), err
    assert flag in err, err


# -- a reader that goes away, help, version ----------------------------------------------------


@pytest.mark.parametrize(
    "argv",
    [
        ["inspect", str(GOLDEN / "gentle-wave.mcap")],
        ["timeline", str(GOLDEN / "gentle-wave.mcap")],
        ["export", str(GOLDEN / "gentle-wave.mcap"), "--format", "csv"],
        ["recover", str(GOLDEN / "gentle-wave.mcap"), "-o", "{tmp}/fixed.mcap"],
    ],
)
def test_a_closed_pipe_ends_the_command_quietly(argv: list[str], tmp_path: Path) -> None:
    """`arena timeline FILE | head -1`, the reader gone before the command writes: it stops
    at its first write, says nothing and exits as a program killed by SIGPIPE does."""
    reader, writer = os.pipe()
    os.close(reader)  # gone before anything is written: every write fails with EPIPE
    try:
        done = subprocess.run(
            [*ARENA, *(a.format(tmp=tmp_path) for a in argv)],
            stdout=writer,
            stderr=subprocess.PIPE,
            env={**os.environ, "PYTHONPATH": str(ROOT)},
            timeout=60,
        )
    finally:
        os.close(writer)
    assert done.stderr == b""
    assert done.returncode == cli.BROKEN_PIPE_STATUS


def test_help_names_every_command_and_only_those(capsys: pytest.CaptureFixture[str]) -> None:
    names = set(cli.command_names(cli.build_parser()))
    assert {"serve", "inspect", "timeline", "replay", "bench", "estop-test"} <= names
    with pytest.raises(SystemExit) as done:
        cli.main(["--help"])
    assert done.value.code == 0
    description = capsys.readouterr().out.split("positional arguments")[0]
    assert set(re.findall(r"`(?:arena )?([a-z][a-z-]*)`", description)) - {"arena"} == names
    for name in sorted(names):
        with pytest.raises(SystemExit):
            cli.main([name, "--help"])
        for mentioned in re.findall(r"`arena ([a-z][a-z-]*)", capsys.readouterr().out):
            assert mentioned in names, (name, mentioned)


def test_bench_help_lists_every_scenario(capsys: pytest.CaptureFixture[str]) -> None:
    from arena.bench import LONG_SCENARIOS, SCENARIOS

    assert (*SCENARIOS, *LONG_SCENARIOS) == cli.BENCH_SCENARIOS
    with pytest.raises(SystemExit):
        cli.main(["bench", "--help"])
    words = set(re.findall(r"[a-z]+", capsys.readouterr().out))
    assert set(SCENARIOS) | set(LONG_SCENARIOS) <= words


@pytest.mark.parametrize(
    ("argv", "flag"),
    [(["sim-bus", "--ids", "1,x"], "--ids"), (["bench", "sock"], "SCENARIO")],
)
def test_bad_arguments_are_refused_by_name(
    argv: list[str], flag: str, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as done:
        cli.main(argv)
    assert done.value.code == 2
    err = capsys.readouterr().err
    assert flag in err and "Traceback" not in err, err


def test_version_and_python_dash_m() -> None:
    import arena

    done = subprocess.run(
        [sys.executable, "-m", "arena", "--version"],
        capture_output=True,
        text=True,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
        cwd=ROOT,
    )
    assert done.returncode == 0 and done.stdout == f"arena {arena.__version__}\n", done
