"""Moving a simulated arm by hand (issue 61): `arena sim-bus --control PORT`. The control's rules
on a clock of the test's own, its socket's bounds with a hostile client, a leader on a
simulated bus moved through the socket driving a follower on a real server, and the command."""

from __future__ import annotations

import itertools
import json
import os
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Awaitable, Callable, Iterator
from pathlib import Path

import pytest
import trio

from arena.robot.model import load_robot_model
from arena.servo import sim_control
from arena.servo.calibration import Calibration
from arena.servo.sim_control import SimControl
from arena.servo.sim_pty import PtySimBus
from tests.conftest import RunningServer
from tests.hardware import eventually, running_sim

StartServer = Callable[..., Awaitable[RunningServer]]
MODEL = load_robot_model("so-101")
STEP = 360 / 4096  # one servo step in degrees


class Clock:
    """Time that moves only when the test says."""

    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


@pytest.fixture
def sim(tmp_path: Path) -> Iterator[PtySimBus]:
    yield from running_sim(tmp_path / "arm")


def answer(control: SimControl, message: object, now: float = 0.0) -> dict:
    line = message if isinstance(message, bytes) else json.dumps(message).encode()
    return control.apply(line, now)


def test_a_joint_moves_at_once_and_reads_back(sim: PtySimBus) -> None:
    control = SimControl(sim, MODEL)
    assert answer(control, {"joint": "shoulder_pan", "deg": 30}) == {
        "ok": True,
        "moving": ["shoulder_pan"],
        "duration": 0.0,
    }
    read = answer(control, {"read": True})["joints"]
    assert read["shoulder_pan"] == pytest.approx(30, abs=STEP)
    assert read["elbow_flex"] == pytest.approx(0, abs=STEP)  # the others stay
    answer(control, {"joint": "gripper", "value": 40})
    assert control.read()["gripper"] == pytest.approx(40, abs=0.2)


def test_a_smooth_move_follows_a_minimum_jerk_curve_on_the_clock(sim: PtySimBus) -> None:
    clock = Clock()
    control = SimControl(sim, MODEL, clock=clock)
    goal = {"shoulder_lift": -40.0, "wrist_flex": 20.0}
    reply = answer(control, {"joints": goal, "duration": 2.0}, clock.now)
    assert reply["ok"] and reply["duration"] == 2.0
    assert control.read()["shoulder_lift"] == pytest.approx(0, abs=STEP)  # not yet
    seen = []
    for k in range(1, 21):
        clock.now = k * 0.1
        moving = control.advance(clock.now)
        seen.append(control.read()["shoulder_lift"])
        assert moving == (k < 20)
    assert seen[9] == pytest.approx(-20, abs=STEP)  # half-way at half the time
    assert seen[1] == pytest.approx(-40 * (0.1**3 * (10 - 1.5 + 0.06)), abs=STEP)
    assert all(b <= a + STEP for a, b in itertools.pairwise(seen))  # one way
    assert control.read()["wrist_flex"] == pytest.approx(20, abs=STEP)
    # A new goal mid-way turns from where the joint is.
    answer(control, {"joints": {"shoulder_lift": 0}, "duration": 1.0}, clock.now)
    clock.now += 1.0
    control.advance(clock.now)
    assert control.read()["shoulder_lift"] == pytest.approx(0, abs=STEP)


@pytest.mark.parametrize(
    ("line", "code", "words"),
    [
        (b"not json", "INVALID_JSON", "not JSON"),
        (b"[1, 2]", "INVALID_BODY", "one JSON object"),
        (b'{"joint": "elbow", "deg": 3}', "UNKNOWN_JOINT", "shoulder_pan, shoulder_lift"),
        (b'{"joint": "elbow_flex", "deg": 300}', "OUT_OF_RANGE", "-96.8 deg to 96.8 deg"),
        (b'{"joint": "gripper", "value": 101}', "OUT_OF_RANGE", "0.0% to 100.0%"),
        (b'{"joint": "elbow_flex", "deg": true}', "OUT_OF_RANGE", "elbow_flex"),
        (b'{"joint": "elbow_flex", "deg": NaN}', "OUT_OF_RANGE", "elbow_flex"),
        (b'{"joints": {"elbow_flex": 3}, "duration": 61}', "INVALID_BODY", "0 to 60"),
        (b'{"joints": {"elbow_flex": 3}, "duration": -1}', "INVALID_BODY", "0 to 60"),
        (b'{"joints": {}}', "INVALID_BODY", "No joint"),
        (b'{"joint": "elbow_flex"}', "INVALID_BODY", '"deg"'),
        (b'{"move": 1}', "INVALID_BODY", '{"read": true}'),
    ],
)
def test_a_bad_line_gets_a_code_and_a_sentence_and_moves_nothing(
    sim: PtySimBus, line: bytes, code: str, words: str
) -> None:
    control = SimControl(sim, MODEL)
    before = control.read()
    reply = answer(control, line)
    assert reply["ok"] is False and reply["error"] == code, reply
    assert words in reply["message"], reply
    assert control.read() == before


def talk(connection: socket.socket, *messages: object) -> list[dict]:
    """Send lines, read one answer for each."""
    data = b"".join(
        (m if isinstance(m, bytes) else json.dumps(m).encode()) + b"\n" for m in messages
    )
    connection.sendall(data)
    reader = connection.makefile("rb")
    return [json.loads(reader.readline()) for _ in messages]


@pytest.fixture
def served(sim: PtySimBus) -> Iterator[tuple[int, Clock]]:
    """The control of `sim` served on a free port, on a clock that stands still (no line is
    ever allowed by time passing: the rate limit is exact)."""
    clock = Clock()
    stop = threading.Event()
    server = SimControl(sim, MODEL, clock=clock).serve(0, stop)
    try:
        yield server.port, clock
    finally:
        stop.set()


def connect(port: int) -> socket.socket:
    return socket.create_connection(("127.0.0.1", port), timeout=30)


def test_the_socket_answers_each_line_and_limits_the_rate(served: tuple[int, Clock]) -> None:
    port, _ = served
    with connect(port) as connection:
        replies = talk(connection, *[{"read": True}] * (sim_control.BURST + 5))
    assert all(r["ok"] for r in replies[: sim_control.BURST])
    assert {r["error"] for r in replies[sim_control.BURST :]} == {"RATE_LIMITED"}


def test_a_line_too_long_closes_the_connection(served: tuple[int, Clock]) -> None:
    port, _ = served
    with connect(port) as connection:
        connection.sendall(b"x" * (sim_control.MAX_LINE + 10))
        reader = connection.makefile("rb")
        reply = json.loads(reader.readline())
        assert reply["error"] == "LINE_TOO_LONG"
        assert reader.readline() == b""  # closed


def test_more_clients_than_allowed_are_told_so(served: tuple[int, Clock]) -> None:
    port, _ = served
    clients = [connect(port) for _ in range(sim_control.MAX_CLIENTS)]
    try:
        for client in clients:  # each is being served
            assert talk(client, {"read": True})[0]["ok"]
        with connect(port) as extra:
            reply = json.loads(extra.makefile("rb").readline())
            assert reply["error"] == "TOO_MANY_CLIENTS"
        clients.pop().close()

        def served_again() -> bool:
            try:
                with connect(port) as again:
                    return bool(talk(again, {"read": True})[0]["ok"])
            except OSError:  # told off and closed while the line was on its way
                return False

        deadline = time.monotonic() + 30  # (a poll for the freed place, generous)
        while not served_again():
            assert time.monotonic() < deadline, "the closed client's place was never freed"
            time.sleep(0.01)
    finally:
        for client in clients:
            client.close()


@pytest.fixture
def follower(tmp_path: Path) -> Iterator[PtySimBus]:
    yield from running_sim(tmp_path / "follower")


async def test_a_leader_moved_through_the_socket_drives_a_follower(
    start_server: StartServer, sim: PtySimBus, follower: PtySimBus, tmp_path: Path
) -> None:
    """Issue 61: a simulated leader, moved by a script through its control socket, is a
    usb-master; the follower, a usb-slave on another simulated bus, goes where it is moved."""
    ids = {j.name: j.servo_id for j in MODEL.joints}
    folder = tmp_path / "calibration"
    Calibration.identity(ids, "so-101").save(folder / "arm.json")
    Calibration.identity(ids, "so-101").save(folder / "arm-leader.json")
    stop = threading.Event()
    port = SimControl(sim, MODEL).serve(0, stop).port
    try:
        server = await start_server(calibration_dir=str(folder))
        async with server.client() as http:
            made = await http.post("/api/robots", json={"id": "arm", "robot_type": "so-101"})
            assert made.status_code == 201, made.text
            slave = {"type": "usb-slave", "port": str(follower.link)}
            attached = await http.post("/api/robots/arm/slaves", json=slave)
            assert attached.status_code == 201, attached.text

            async def joined() -> bool:
                robot = (await http.get("/api/robots/arm")).json()
                return bool(robot["slaves"]) and not robot["slaves"][0].get("joining")

            await eventually(joined, what="the follower joined")
            master = {"type": "usb-master", "port": str(sim.link)}
            leading = await http.post("/api/robots/arm/master", json=master)
            assert leading.status_code == 201, leading.text
            goal = {"shoulder_pan": 25.0, "elbow_flex": -30.0, "gripper": 60.0}

            def move() -> list[dict]:
                with connect(port) as connection:
                    return talk(connection, {"joints": goal, "duration": 0.5})

            reply = await trio.to_thread.run_sync(move)
            assert reply[0]["ok"], reply

            async def followed() -> bool:
                joints = (await http.get("/api/robots/arm/joints")).json()
                read = {j["name"]: j["real_value"] for j in joints}
                return all(
                    (value := read[name]) is not None and abs(value - goal[name]) < 1.5
                    for name in goal
                )

            await eventually(followed, what=f"the follower at {goal}")
    finally:
        stop.set()


def test_the_sim_bus_command_serves_the_control_and_says_how(tmp_path: Path) -> None:
    link = tmp_path / "ttyLEADER"
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    command = [sys.executable, "-m", "arena.cli", "sim-bus", "--link", str(link)]
    process = subprocess.Popen(
        [*command, "--robot-type", "so-101", "--control", "0"],
        stdout=subprocess.PIPE,
        stdin=subprocess.DEVNULL,
        text=True,
        env=env,
    )
    try:
        assert process.stdout is not None
        assert "servos 1,2,3,4,5,6" in process.stdout.readline()
        usage = process.stdout.readline()
        assert usage.startswith("control: JSON lines on 127.0.0.1:"), usage
        port = int(usage.split("127.0.0.1:")[1].split(",")[0])
        shown = "".join(process.stdout.readline() for _ in range(4))
        assert '"duration"' in shown and "shoulder_pan, shoulder_lift" in shown
        with connect(port) as connection:
            replies = talk(connection, {"joint": "wrist_flex", "deg": -12.5}, {"read": True}, b"{")
        assert replies[0]["ok"]
        assert replies[1]["joints"]["wrist_flex"] == pytest.approx(-12.5, abs=STEP)
        assert replies[2]["error"] == "INVALID_JSON"
    finally:
        process.terminate()
        process.wait(timeout=10)
    assert process.returncode == 0


def test_keys_pick_a_joint_and_move_it(sim: PtySimBus) -> None:
    clock = Clock()
    control = SimControl(sim, MODEL, clock=clock)
    keys = iter(["2", "+", "+", "-", "r", "9", "0", "?", ""])
    said: list[str] = []
    seen: list[float] = []

    def read_key() -> str:
        clock.now += 1.0  # each key after the last move is done
        control.advance(clock.now)
        seen.append(control.read()["shoulder_lift"])
        return next(keys)

    sim_control.key_loop(control, read_key, said.append)
    step = sim_control.KEY_STEP
    assert seen[2:5] == pytest.approx([step, 2 * step, step], abs=STEP)
    assert said[0] == "shoulder_lift selected"
    assert json.loads(said[4])["shoulder_lift"] == pytest.approx(step, abs=STEP)  # r
    assert seen[-1] == pytest.approx(0, abs=STEP)  # 9 picks nothing (six joints); 0 sends it home
    assert said[-1].startswith("keys: 1 shoulder_pan, 2 shoulder_lift")


def test_the_sim_bus_command_takes_keys_from_its_terminal(tmp_path: Path) -> None:
    """`arena sim-bus --keys` on a terminal of the test's own (a pty): single keys move a
    joint, Ctrl-C stops it and the terminal is given back as it was."""
    import pty
    import select
    import signal
    import termios

    link = tmp_path / "ttyKEYS"
    command = [sys.executable, "-m", "arena.cli", "sim-bus", "--link", str(link)]
    pid, terminal = pty.fork()
    if pid == 0:  # the child: the command on the pty
        os.execve(
            sys.executable,
            [*command, "--robot-type", "so-101", "--keys"],
            {**os.environ, "PYTHONUNBUFFERED": "1"},
        )
    shown = b""

    def until(text: bytes, after: int = 0) -> None:
        """Read the terminal until `text` shows (after byte `after`)."""
        nonlocal shown
        deadline = time.monotonic() + 60  # a loaded machine starts Python slowly
        while text not in shown[after:]:
            assert time.monotonic() < deadline, (text, shown)
            if select.select([terminal], [], [], 0.5)[0]:
                shown += os.read(terminal, 4096)

    try:
        before = termios.tcgetattr(terminal)
        until(b"keys: 1 shoulder_pan")
        assert not termios.tcgetattr(terminal)[3] & termios.ICANON  # one key at a time
        for key, answer in ((b"3", b"elbow_flex selected"), (b"-", b"elbow_flex -> -5")):
            os.write(terminal, key)
            until(answer)
        deadline = time.monotonic() + 60
        while True:  # read (r) until the step, a smooth one, is done
            assert time.monotonic() < deadline, shown
            start = len(shown)
            os.write(terminal, b"r")
            until(b"}", after=start)
            if b'"elbow_flex": -5' in shown[start:]:
                break
        os.kill(pid, signal.SIGINT)
        _, status = os.waitpid(pid, 0)
        pid = 0
        assert os.WIFEXITED(status) and os.WEXITSTATUS(status) == 0
        assert termios.tcgetattr(terminal)[3] == before[3]  # given back
    finally:
        if pid:
            os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)
        os.close(terminal)
