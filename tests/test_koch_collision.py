"""Issue 57 through a real server with the Koch on the simulated Dynamixel bus: an arm read at
shoulder_lift -10, elbow_flex 12.5, wrist_flex -7.5 (near the middle of its calibrated range)
pans 5 degrees; an arm the model puts in the table may move out of it, not deeper in."""

from __future__ import annotations

import json
from collections.abc import Awaitable, Callable, Iterator
from pathlib import Path

import pytest

from arena.servo.sim_pty import PtySimBus
from tests.conftest import RunningServer
from tests.hardware import eventually, running_sim
from tests.lerobot_arms import NAMES, attach_arm, joined, place_arm, real_values

pytest.importorskip("dynamixel_sdk")
from arena.dynamixel.sim import SimBus

StartServer = Callable[..., Awaitable[RunningServer]]

#: A LeRobot Koch calibration file (half-turn homings, pan and roll a whole turn, the others
#: swept): degrees are (present - middle of the range) * 360 / 4095, present = actual + offset.
_FIELDS = ("id", "drive_mode", "homing_offset", "range_min", "range_max")
CALIBRATION = {
    name: dict(zip(_FIELDS, values, strict=True))
    for name, values in {
        "shoulder_pan": (1, 0, 247, 0, 4095),
        "shoulder_lift": (2, 0, -1353, 1060, 3010),
        "elbow_flex": (3, 0, 947, 1100, 3000),
        "wrist_flex": (4, 0, -153, 900, 3150),
        "wrist_roll": (5, 0, 1447, 0, 4095),
        "gripper": (6, 0, 547, 1990, 2950),
    }.items()
}
NORMAL = {"shoulder_lift": -10.0, "elbow_flex": 12.5, "wrist_flex": -7.5}
#: Where the Koch's model has the hand some 6 cm into the table.
INSIDE = {"shoulder_lift": -20.0, "elbow_flex": 30.0, "wrist_flex": -40.0}


@pytest.fixture
def sim(tmp_path: Path) -> Iterator[PtySimBus]:
    yield from running_sim(tmp_path, bus=SimBus())


def actual_steps(degrees: dict[str, float]) -> dict[int, int]:
    """The servo steps (before homing) at which LeRobot's calibration reads `degrees` (other
    arm joints 0, the gripper half open)."""
    steps = {}
    for name, cal in CALIBRATION.items():
        middle = (cal["range_min"] + cal["range_max"]) / 2
        turn = 0.0 if name == "gripper" else degrees.get(name, 0.0) * 4095 / 360
        present = middle + turn
        steps[cal["id"]] = round(present) - cal["homing_offset"]
    return steps


async def arm_at(http: object, sim: PtySimBus, tmp_path: Path, degrees: dict[str, float]) -> None:
    """Robot `arm`, a koch, its usb-slave on the simulated bus with the arm standing at
    `degrees`, joined (the robot adopted that pose)."""
    place_arm(sim, actual_steps(degrees))
    path = tmp_path / "arm.json"
    path.write_text(json.dumps(CALIBRATION))
    attached = await attach_arm(http, sim, "koch", str(path))
    assert attached.status_code == 201, attached.text
    await eventually(lambda: joined(http), what="the arm joined")
    read = await real_values(http)
    for name, value in degrees.items():
        assert read[name] == pytest.approx(value, abs=0.2), (name, read)


async def at(http: object, goal: dict[str, float]) -> bool:
    read = await real_values(http)
    return all((v := read[n]) is not None and abs(v - goal[n]) < 1.0 for n in goal)


async def test_a_koch_read_near_the_middle_of_its_range_pans_5_degrees(
    start_server: StartServer, sim: PtySimBus, tmp_path: Path
) -> None:
    server = await start_server()
    async with server.client() as http:
        await arm_at(http, sim, tmp_path, NORMAL)
        pan = (await real_values(http))["shoulder_pan"]
        assert pan is not None
        move = {"joints": [{"name": "shoulder_pan", "value": pan + 5.0}]}
        answer = await http.put("/api/robots/arm/joints", json=move)
        assert answer.status_code == 200, answer.text
        assert answer.json()["status"] == "accepted"
        await eventually(lambda: at(http, {"shoulder_pan": pan + 5.0, **NORMAL}), what="panned")


async def test_an_arm_in_the_table_may_move_out_not_deeper_in(
    start_server: StartServer, sim: PtySimBus, tmp_path: Path
) -> None:
    server = await start_server()
    async with server.client() as http:
        await arm_at(http, sim, tmp_path, INSIDE)
        deeper = {"joints": [{"name": "shoulder_lift", "value": -25.0}]}
        refused = await http.put("/api/robots/arm/joints", json=deeper)
        assert refused.status_code == 422, refused.text
        body = refused.json()["error"]
        assert body["code"] == "COLLISION", body
        assert "already collides" in body["message"] and "decreases" in body["message"]
        assert "hand and floor -" in body["message"]
        out = {"shoulder_lift": 10.0, "elbow_flex": 0.0}
        answer = await http.put(
            "/api/robots/arm/joints",
            json={"joints": [{"name": n, "value": v} for n, v in out.items()]},
        )
        assert answer.status_code == 200, answer.text
        assert answer.json()["status"] == "accepted"
        assert "out of a collision in the model: hand and floor -" in answer.json()["message"]
        await eventually(lambda: at(http, out), what="the arm out of the table")
        # Out of the table, the guard is as ever: back into it is refused as a collision.
        back = {
            "joints": [
                {"name": "shoulder_lift", "value": -20.0},
                *[{"name": n, "value": v} for n, v in INSIDE.items() if n != "shoulder_lift"],
            ]
        }
        again = await http.put("/api/robots/arm/joints", json=back)
        assert again.status_code == 422 and "already collides" not in again.text
        assert set(NAMES) == set(await real_values(http))
