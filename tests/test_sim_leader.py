"""A simulated leader arm the server owns (`arena serve --sim-leader`, issue 61), moved over REST
(`PUT /api/robots/{id}/leader/joints`) as a hand moves a real one: its usb-master reads it and
drives the robot through every rule, as the robot's master and as an intervention on a running
one. Then the refusals: no leader, a leader that is hardware, unknown joints, values out of
range, bad bodies, the rate, the role, a foreign page. All through a real server."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from arena.cli import build_parser
from arena.server.sim_leaders import SimLeader
from arena.servo.sim_pty import PtySimBus
from tests.conftest import RunningServer, eventually
from tests.hardware import running_sim
from tests.test_intervention_server import SEQUENCE, Start
from tests.test_users import SECRET, bearer, token

ROBOT = "/api/robots/demo-arm"
OPERATOR = bearer(token("operator", sub="olga"))
VIEWER = bearer(token("viewer", sub="vic"))


@pytest.fixture
def real_leader(tmp_path: Path) -> Iterator[PtySimBus]:
    """A leader arm that is not the server's: a bus of the test's own (as an arm on USB)."""
    yield from running_sim(tmp_path / "real")


async def leader_server(start_server: Start, tmp_path: Path) -> RunningServer:
    (tmp_path / "jwt-secret").write_bytes(SECRET)
    return await start_server(
        demo=True,
        sim_leader="so-arm100",
        jwt_secret_file=str(tmp_path / "jwt-secret"),
        calibration_dir=str(tmp_path / "calibration"),
    )


def sim_of(server: RunningServer) -> SimLeader:
    (leader,) = server.app.sim_leaders.leaders
    assert isinstance(leader, SimLeader)
    return leader


async def follows(http: httpx.AsyncClient, goal: dict[str, float]) -> None:
    """Wait until the robot's measured joints are at `goal`."""

    async def there() -> bool:
        joints = (await http.get(f"{ROBOT}/joints", headers=OPERATOR)).json()
        read = {j["name"]: j["real_value"] for j in joints}
        return all(
            read[name] is not None and abs(read[name] - value) < 1.5 for name, value in goal.items()
        )

    await eventually(there, what=f"the robot at {goal}")


def move(goal: dict[str, float], duration: float = 300) -> dict[str, Any]:
    return {"joints": [{"name": k, "value": v} for k, v in goal.items()], "duration": duration}


def error_of(answer: httpx.Response) -> tuple[int, str]:
    return answer.status_code, answer.json()["error"]["code"]


async def test_the_simulated_leader_drives_the_robot_and_corrects_a_running_master(
    start_server: Start, tmp_path: Path
) -> None:
    server = await leader_server(start_server, tmp_path)
    port = sim_of(server).port
    async with server.client(headers=OPERATOR) as http:
        shown = (await http.get(f"{ROBOT}/leader")).json()
        assert shown == {"simulated": [{"port": port, "robot_type": "so-arm100"}], "leader": None}
        attached = await http.post(f"{ROBOT}/master", json={"type": "usb-master", "port": port})
        assert attached.status_code == 201, attached.text
        leader = (await http.get(f"{ROBOT}/leader")).json()["leader"]
        assert leader["id"] == attached.json()["id"]
        assert leader["simulated"] is True and leader["driving"] is True
        names = [joint["name"] for joint in leader["joints"]]
        assert names == ["Rotation", "Pitch", "Elbow", "Wrist_Pitch", "Wrist_Roll", "Jaw"]
        assert all(j["min"] < j["max"] for j in leader["joints"])
        # Teleoperation: the leader moved from the API, the robot follows through its master.
        goal = {"Rotation": 25.0, "Elbow": -20.0}
        moved = await http.put(f"{ROBOT}/leader/joints", json=move(goal))
        assert moved.status_code == 200, moved.text
        assert moved.json() == {
            "leader": leader["id"],
            "moving": ["Elbow", "Rotation"],
            "duration": 300,
        }
        await follows(http, goal)
        read = (await http.get(f"{ROBOT}/leader")).json()["leader"]["joints"]
        assert abs(next(j for j in read if j["name"] == "Rotation")["value"] - 25.0) < 0.2
        assert (await http.delete(f"{ROBOT}/master")).status_code == 200
        # A correction: a running master paused, the simulated leader intervenes and drives.
        assert (await http.post(f"{ROBOT}/master", json=SEQUENCE)).status_code == 201
        master = {"type": "usb-master", "port": port}
        taken = await http.post(f"{ROBOT}/intervention", json={"master": master})
        assert taken.status_code == 201, taken.text
        goal = {"Rotation": -30.0, "Pitch": 15.0}
        moved = await http.put(f"{ROBOT}/leader/joints", json=move(goal))
        assert moved.status_code == 200, moved.text
        assert moved.json()["leader"] == taken.json()["intervening"]
        await follows(http, goal)
        robot = (await http.get(ROBOT)).json()
        assert robot["master"]["kind"] == "usb-master"
        assert robot["paused_master"]["kind"] == "mock-sequence"
        assert (await http.delete(f"{ROBOT}/intervention")).status_code == 200
        # Handed back: the sequence drives again and the leader is no longer the robot's.
        gone = await http.put(f"{ROBOT}/leader/joints", json=move(goal))
        assert error_of(gone) == (404, "NO_LEADER")


async def test_every_hostile_move_is_refused_with_its_code(
    start_server: Start, tmp_path: Path, real_leader: PtySimBus
) -> None:
    server = await leader_server(start_server, tmp_path)
    sim = sim_of(server)
    goal = move({"Rotation": 10.0})
    async with server.client(headers=OPERATOR) as http:
        nobody = await http.put(f"{ROBOT}/leader/joints", json=goal)
        assert error_of(nobody) == (404, "NO_LEADER")
        # A leader arm that is hardware (not the server's simulator) is never written to.
        real = {"type": "usb-master", "port": str(real_leader.link)}
        assert (await http.post(f"{ROBOT}/master", json=real)).status_code == 201
        hardware = await http.put(f"{ROBOT}/leader/joints", json=goal)
        assert error_of(hardware) == (409, "LEADER_NOT_SIMULATED")
        shown = (await http.get(f"{ROBOT}/leader")).json()["leader"]
        assert shown["simulated"] is False and "joints" not in shown
        assert (await http.delete(f"{ROBOT}/master")).status_code == 200
        ours = {"type": "usb-master", "port": sim.port}
        assert (await http.post(f"{ROBOT}/master", json=ours)).status_code == 201
        before = (await http.get(f"{ROBOT}/leader")).json()["leader"]["joints"]
        for body, expected in [
            (move({"Elbw": 10.0}), (422, "UNKNOWN_JOINT")),
            (move({"Rotation": 500.0}), (422, "INVALID_VALUE")),
            (move({"Jaw": -1.0e9}), (422, "INVALID_VALUE")),
            (move({"Rotation": 10.0}, duration=60_001), (422, "INVALID_BODY")),
            (move({"Rotation": 10.0}, duration=-1), (422, "INVALID_BODY")),
            ({"joints": []}, (422, "INVALID_BODY")),
            ({"joints": [{"name": "Rotation", "value": 1}] * 2}, (422, "INVALID_BODY")),
            ({"joints": [{"name": "Rotation", "value": "far"}]}, (422, "INVALID_BODY")),
            ({"joints": [{"name": "Rotation", "value": 1}], "speed": 3}, (400, "UNKNOWN_FIELD")),
        ]:
            answer = await http.put(f"{ROBOT}/leader/joints", json=body)
            assert error_of(answer) == expected, (body, answer.text)
        huge = b'{"joints": [{"name": "Rotation", "value": 1e999}]}'
        infinite = await http.put(
            f"{ROBOT}/leader/joints", content=huge, headers={"Content-Type": "application/json"}
        )
        assert error_of(infinite) == (422, "INVALID_BODY"), infinite.text  # (no finite number)
        # The role, and pages: a viewer may look, not move; another site's page may not move.
        assert (await http.get(f"{ROBOT}/leader", headers=VIEWER)).status_code == 200
        viewer = await http.put(f"{ROBOT}/leader/joints", json=goal, headers=VIEWER)
        assert error_of(viewer) == (403, "FORBIDDEN")
        page = await http.put(
            f"{ROBOT}/leader/joints", json=goal, headers={"Origin": "https://evil.example"}
        )
        assert error_of(page) == (403, "ORIGIN_NOT_ALLOWED")
        rebound = await http.put(
            f"{ROBOT}/leader/joints", json=goal, headers={"Host": "evil.example"}
        )
        assert error_of(rebound) == (403, "HOST_NOT_ALLOWED")
        after = (await http.get(f"{ROBOT}/leader")).json()["leader"]["joints"]
        assert after == before, "a refused move moved the leader"
        # The rate: a burst passes, the next is refused (no refill: the bound alone decides).
        sim.rate = 1e-9
        for _ in range(int(sim.burst)):  # (no move has passed yet: the bucket is full)
            assert (await http.put(f"{ROBOT}/leader/joints", json=goal)).status_code == 200
        over = await http.put(f"{ROBOT}/leader/joints", json=goal)
        assert error_of(over) == (429, "RATE_LIMITED")


def test_the_rate_refills_at_its_pace() -> None:
    """The bucket on a clock of the test's own: a burst, then one move per 1/rate seconds."""
    leader = SimLeader("so-arm100", Path("/nonexistent"), None)  # type: ignore[arg-type]
    allowed = [leader.allow(0.0) for _ in range(int(leader.burst) + 1)]
    assert allowed == [True] * int(leader.burst) + [False]
    assert leader.allow(1.0 / leader.rate) and not leader.allow(1.0 / leader.rate)
    assert sum(leader.allow(10.0) for _ in range(100)) == leader.burst  # never more than a burst


@pytest.mark.parametrize(
    ("flags", "expected"),
    [([], None), (["--sim-leader"], "so-arm100"), (["--sim-leader", "so-101"], "so-101")],
)
def test_serve_takes_sim_leader_with_or_without_a_type(
    flags: list[str], expected: str | None
) -> None:
    """`make run`'s `arena serve --demo --sim-leader --port 8080`: the type is optional."""
    args = build_parser().parse_args(["serve", "--demo", *flags, "--port", "8080"])
    assert args.sim_leader == expected and args.port == 8080
