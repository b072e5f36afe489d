"""A lab server that comes back by itself: `arena serve --config lab.toml` in a process of its
own, two arms on simulated buses and a camera, killed with SIGKILL (a power cut) and started
again from the same file: both arms attached and held where they were, no jump, the camera
streaming. The simulated buses live in the test's process, as the arms outlive the server."""

from __future__ import annotations

import os
import signal
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from arena.feetech import registers as reg
from arena.feetech.sim import SimBus
from arena.servo.sim_pty import PtySimBus
from tests.serve_process import ServeProcess, serving

ROOT = Path(__file__).resolve().parent.parent
#: Only a broken start waits this long (a loaded 2-core machine starts in seconds).
PATIENCE = 120.0
#: Steps of a Feetech servo in one degree (4096 a turn).
STEPS_PER_DEGREE = 4096 / 360

LAB = """\
port = 0

[[robots]]
id = "left"

[[robots.slaves]]
id = "arm"
type = "usb-slave"
port = "{left}"

[[robots.cameras]]
name = "top"
source = "test-pattern"
fps = 10

[[robots]]
id = "right"

[[robots.slaves]]
id = "arm"
type = "usb-slave"
port = "{right}"
"""


@pytest.fixture
def sims(tmp_path: Path) -> Iterator[dict[str, PtySimBus]]:
    """Two simulated arms, shared with other processes (the server paces its bus by them)."""
    buses = {
        name: PtySimBus(tmp_path / f"tty-{name}", SimBus(), share=True).start()
        for name in ("left", "right")
    }
    yield buses
    for bus in buses.values():
        bus.close()


def held(served: ServeProcess, robots: list[str]) -> dict[str, dict[str, float]]:
    """Wait until every robot's arm is attached and has joined; each robot's measured pose."""
    deadline = time.monotonic() + PATIENCE
    poses: dict[str, dict[str, float]] = {}
    for robot_id in robots:
        while True:
            answer = httpx.get(f"{served.url}/api/robots/{robot_id}", timeout=10)
            slaves = answer.json().get("slaves", []) if answer.status_code == 200 else []
            if slaves and slaves[0]["connected"] and not slaves[0]["joining"]:
                break
            assert time.monotonic() < deadline, f"{robot_id} not held:\n{served.log}"
            time.sleep(0.05)
        joints = httpx.get(f"{served.url}/api/robots/{robot_id}/joints", timeout=10).json()
        poses[robot_id] = {j["name"]: j["real_value"] for j in joints}
    return poses


def streams(served: ServeProcess) -> bool:
    """The camera's live stream sends two frames."""
    url = f"{served.url}/api/robots/left/cameras/top/stream"
    with httpx.stream("GET", url, timeout=30) as stream:
        seen = b""
        for chunk in stream.iter_bytes():
            seen += chunk
            if seen.count(b"\xff\xd8") >= 2:  # two JPEG starts
                return True
    return False


def presents(sim: PtySimBus) -> dict[int, int]:
    with sim.paused() as bus:
        return {sid: servo.peek(reg.PRESENT_POSITION) for sid, servo in bus.servos.items()}


@pytest.mark.real_io
def test_killed_and_started_again_both_arms_come_back_held_without_a_jump(
    tmp_path: Path, sims: dict[str, PtySimBus], capsys: pytest.CaptureFixture[str]
) -> None:
    lab = tmp_path / "lab.toml"
    lab.write_text(LAB.format(left=sims["left"].link, right=sims["right"].link), encoding="utf-8")
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    argv = ["--config", str(lab), "--no-record"]
    started = time.monotonic()
    with serving(argv, cwd=tmp_path, env=env) as served:
        first_listening = time.monotonic() - started  # (the declared parts are attached)
        held(served, ["left", "right"])
        first_held = time.monotonic() - started
        # Put the left arm somewhere a restart that forgot it would have to leave.
        target = [{"name": "Rotation", "value": 30.0}, {"name": "Pitch", "value": -20.0}]
        moved = httpx.put(f"{served.url}/api/robots/left/joints", json={"joints": target})
        assert moved.json()["status"] == "accepted", moved.text
        deadline = time.monotonic() + PATIENCE
        while True:
            pose = held(served, ["left"])["left"]
            if abs(pose["Rotation"] - 30) < 0.5 and abs(pose["Pitch"] + 20) < 0.5:
                break
            assert time.monotonic() < deadline, pose
            time.sleep(0.1)
        time.sleep(0.5)  # at rest
        before = held(served, ["left", "right"])
        assert streams(served)
        served.process.send_signal(signal.SIGKILL)  # the power cut
        served.process.wait(timeout=30)
    at_kill = {name: presents(sim) for name, sim in sims.items()}
    for sim in sims.values():
        sim.bus.write_log = []  # what the new server commands
    started = time.monotonic()
    with serving(argv, cwd=tmp_path, env=env) as served:
        again_listening = time.monotonic() - started
        after = held(served, ["left", "right"])
        again_held = time.monotonic() - started
        assert streams(served)
        joints = httpx.get(f"{served.url}/api/robots/left/joints", timeout=10).json()
    for robot_id in ("left", "right"):
        for joint, value in before[robot_id].items():
            assert after[robot_id][joint] == pytest.approx(value, abs=0.5), (robot_id, joint)
    # The robot took the arm's pose: its target is where the arm is, not where it started.
    virtual = {j["name"]: j["virtual_value"] for j in joints}
    assert virtual["Rotation"] == pytest.approx(30, abs=0.5)
    assert virtual["Pitch"] == pytest.approx(-20, abs=0.5)
    # Every goal the new server sent lies where the servo was: no jump, not even briefly.
    goal = reg.GOAL_POSITION
    for name, sim in sims.items():
        goals = [
            (sid, goal.decode(data))
            for _, sid, address, data in sim.bus.write_log or []
            if address == goal.address
        ]
        assert goals, f"{name}: no goal written (not held)"
        worst = max(abs(value - at_kill[name][sid]) for sid, value in goals)
        assert worst <= STEPS_PER_DEGREE, f"{name}: a goal {worst} steps from the pose"
        with sim.paused() as bus:
            assert {s.peek(reg.TORQUE_ENABLE) for s in bus.servos.values()} == {1}
    with capsys.disabled():
        print(
            f"\nprocess start to both declared arms held: {first_held:.2f} s "
            f"(first start; listening at {first_listening:.2f} s), {again_held:.2f} s "
            f"(after SIGKILL; listening at {again_listening:.2f} s)"
        )
