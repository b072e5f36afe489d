"""A motion the collision guard stops on its way, after its command was accepted, is reported
to whoever commanded it (issue 57): a WebSocket master gets `stopped`, the robot's details
show it as `last_stop`, the recording holds it (`stop`), and a driver's link counts it.

The case: the so-arm100 turns its Rotation slowly from zero towards 90 degrees (a speed cap,
or a script's duration: the move lasts seconds), and once it is on its way a keep-out box (a
pillar) is put where its hand will be at about 42 degrees. The command was accepted on a
clear way; the box came after, so the guard, checking every target the arm is sent, stops
the arm just short of it. Each test waits for events, not for time: the box goes in once
the robot has sent the arm a target on the way."""

from __future__ import annotations

import functools
import json
from pathlib import Path
from typing import Any

import trio
from trio_websocket import open_websocket_url

from arena.recording.mcap_file import read_recording
from arena.robot import collision
from arena.robot.events import (
    CommandHandled,
    FaultReported,
    MotionStopped,
    RobotEvent,
    TargetsSent,
)
from arena.robot.handle import Robot
from arena.robot.mailbox import EventQueue
from arena.robot.model import RobotModel, load_robot_model
from arena.robot.workspace import Box, Workspace
from tests.conftest import RunningServer, eventually
from tests.test_policy_server import next_event
from tests.test_scripts import attach, run_arena_script, scripted, wait_for_no_master, write
from tests.test_server_ws import receive

ROBOT = "/api/robots/demo-arm"
#: Where the move goes, and its speed cap (deg/s): about 9 s to the goal and 4 s to where
#: the pillar will be, so no loaded machine gets the arm there before the pillar is put.
GOAL, SPEED = 90.0, 10.0
SLOW = {"joints": [{"name": "Rotation", "value": GOAL, "speed": SPEED}]}
#: A pillar on the table where the hand passes at about 42 degrees of Rotation (the arm
#: reaching out straight, every other joint at zero).
PILLAR = {"name": "pillar", "min": [0.25, -0.25, 0.0], "max": [0.40, 0.0, 0.40]}
#: A bound on waits only a broken feature reaches.
WAIT = 30.0


@functools.cache
def guarded() -> tuple[RobotModel, collision.CollisionModel]:
    """The so-arm100's model and the guard's own collision model of it."""
    model = load_robot_model("so-arm100")
    guard = collision.for_model(model)
    assert guard is not None
    return model, guard


def hits(rotation: float, pillar: bool = True) -> bool:
    """Whether the guard's own model of the so-arm100, at `rotation` and every other joint
    at zero, meets something in the workspace the server has (its table, and the pillar)."""
    model, guard = guarded()
    box = Box(PILLAR["name"], tuple(PILLAR["min"]), tuple(PILLAR["max"]))  # type: ignore[arg-type]
    floor, margin = model.workspace.floor, model.workspace.margin
    workspace = Workspace(floor=floor, keep_out=(box,) if pillar else (), margin=margin)
    pose = {j.name: 0.0 for j in model.joints} | {"Rotation": rotation}
    urdf = {j.urdf_name: j.to_urdf(pose[j.name]) for j in model.joints}
    return guard.assess(urdf, workspace)[0] is not None


#: Where the stop must hold the arm (just short of it): the first Rotation, to a tenth of a
#: degree, at which the arm meets the pillar.
HIT = next(tenths / 10 for tenths in range(901) if hits(tenths / 10))


def test_the_pillar_is_where_the_tests_say() -> None:
    """The scene: without the pillar the way to the goal is clear (the command is accepted);
    with it, the arm meets it on the way, far enough out that the arm is not there yet when
    the pillar is put (the stop happens on the way, not at once), and the way back past zero
    stays clear."""
    assert not any(hits(tenths / 10, pillar=False) for tenths in range(0, 901, 5))
    assert 40.0 < HIT < GOAL and hits(GOAL)
    assert not any(hits(tenths / 10) for tenths in range(-100, int(HIT * 10), 5))


def on_the_way(event: RobotEvent) -> bool:
    return isinstance(event, TargetsSent) and 0.0 < event.joints.get("Rotation", 0.0) < HIT


async def block_the_way(
    http: Any, robot: Robot, moving: EventQueue[RobotEvent], timeout: float = WAIT
) -> None:
    """Once the robot has sent the arm a target on its way (its command accepted), the
    pillar is put in the workspace (the robot type's table kept: a PUT of boxes alone keeps
    it)."""
    with trio.fail_after(timeout):
        while not on_the_way(await moving.get()):
            pass
    await put_pillar(http, robot)


async def put_pillar(http: Any, robot: Robot) -> None:
    """The pillar put in the workspace, the robot type's table kept."""
    put = await http.put(f"/api/robots/{robot.robot_id}/workspace", json={"keep_out": [PILLAR]})
    assert put.status_code == 200, put.text
    assert put.json()["floor"] == robot.model.workspace.floor
    assert [box.name for box in robot.workspace.keep_out] == ["pillar"]


def check_stop(stop: dict[str, Any], source: str) -> None:
    """The stop as the details show it: who, why, what, and where the arm holds (short of
    its goal, just short of the pillar, after having moved on its way)."""
    assert stop["source"] == source and stop["code"] == "COLLISION", stop
    assert "pillar" in stop["blocked"], stop
    assert "pillar" in stop["message"] and "holds at Rotation" in stop["message"], stop
    assert stop["goals"]["Rotation"] == GOAL  # where it was going
    held = stop["joints"]["Rotation"]
    assert HIT - 5.0 < held < HIT, (held, HIT)  # on the way, short of the pillar


async def test_a_rest_command_the_guard_stops_on_its_way_is_shown_and_recorded(
    server: RunningServer,
) -> None:
    robot = server.app.manager.get("demo-arm")
    async with (
        server.client() as http,
        open_websocket_url(f"{server.ws_url}/ws/robots/demo-arm/state") as viewer,
    ):
        assert (await http.get(ROBOT)).json()["last_stop"] is None
        faults: list[dict[str, Any]] = []

        # The viewer reads as it goes, as the dashboard does (one that stops reading falls
        # behind over the seconds of the move, and a viewer behind is not sent faults).
        async def watch() -> None:
            faults.append(await receive(viewer, "fault", timeout=WAIT))

        async with trio.open_nursery() as nursery:
            nursery.start_soon(watch)
            with robot.subscribe(kinds=[MotionStopped]) as events, trio.fail_after(WAIT):
                with robot.subscribe(kinds=[TargetsSent]) as moving:
                    moved = await http.put(f"{ROBOT}/joints", json=SLOW)
                    assert moved.status_code == 200, moved.text
                    assert moved.json()["status"] == "accepted" and not moved.json()["clamped"]
                    await block_the_way(http, robot, moving)
                stopped = await events.get()
        assert isinstance(stopped, MotionStopped) and stopped.source == "manual"
        # A viewer (the dashboard, whose sliders command as `manual`) sees it as a warning.
        told = faults[0]["data"]
        assert (told["peer_id"], told["code"], told["severity"]) == (
            "manual",
            "COLLISION",
            "warning",
        )
        assert "pillar" in told["message"], told
        details = (await http.get(ROBOT)).json()
        check_stop(details["last_stop"], "manual")
        held = {j["name"]: j["virtual_value"] for j in (await http.get(f"{ROBOT}/joints")).json()}
        assert abs(held["Rotation"] - details["last_stop"]["joints"]["Rotation"]) < 1e-3
        assert not robot.core.motion.moving  # it holds there, not going on
        # Recorded: read back from the file with its own reader.
        name = (await http.post("/api/recordings/current/stop")).json()["stopped"]
    messages = read_recording(Path(server.app.recorder.folder) / name).messages
    (record,) = [m for m in messages if m.kind == "stop"]
    assert record.robot_id == "demo-arm" and record.data["source"] == "manual"
    assert record.data["code"] == "COLLISION" and "pillar" in record.data["blocked"]
    assert record.data["goals"]["Rotation"] == GOAL and record.data["joints"]["Rotation"] < HIT


async def test_a_websocket_master_is_told_its_accepted_motion_was_stopped(
    server: RunningServer,
) -> None:
    robot = server.app.manager.get("demo-arm")
    async with (
        server.client() as http,
        open_websocket_url(f"{server.ws_url}/ws/master/demo-arm?id=mover") as ws,
    ):
        await receive(ws, "state")
        link = robot._actor.peers.master.link
        with (
            robot.subscribe(kinds=[CommandHandled]) as handled,
            robot.subscribe(kinds=[TargetsSent]) as moving,
        ):
            await ws.send_message(json.dumps({"type": "command", "data": SLOW}))
            ack = await receive(ws, "ack", timeout=WAIT)
            assert ack["data"]["status"] == "accepted", ack
            assert (await handled.get()).result.accepted
            await block_the_way(http, robot, moving)
        stopped = await receive(ws, "stopped", timeout=WAIT)
        data = stopped["data"]
        assert data["code"] == "COLLISION" and "pillar" in data["blocked"], data
        assert "holds at" in data["message"], data
        assert link.stops == 1
        check_stop((await http.get(ROBOT)).json()["last_stop"], "mover")
        # A new command moves it again (the way back is clear): no further stop.
        back = {"type": "command", "data": {"joints": [{"name": "Rotation", "value": 0.0}]}}
        await ws.send_message(json.dumps(back))
        assert (await receive(ws, "ack", timeout=WAIT))["data"]["status"] == "accepted"
        await eventually(lambda: not robot.core.motion.moving, what="the arm back at zero")
        assert link.stops == 1 and robot.core.motion.goals["Rotation"] == 0.0


#: A script whose first move (slow: 9 s) the guard stops once the pillar is in its way: it
#: catches the COLLISION and moves on, away from the pillar.
REACH = f"""\
from arena.script import ScriptError, move_joints

try:
    move_joints({{"Rotation": {GOAL}}}, duration={GOAL / SPEED})
except ScriptError as error:
    print("stopped", error.code)
    move_joints({{"Rotation": -10}})
move_joints({{"Nope": 1}})
"""


async def test_a_script_waiting_for_its_move_is_told_the_guard_stopped_it(
    start_server: Any, tmp_path: Path
) -> None:
    """A script's move waits until the arm is there: one the guard holds short raises
    COLLISION at the script's line (it may catch it), where it returned as if it had arrived."""
    server = await scripted(start_server, tmp_path)
    write(tmp_path / "scripts", "reach.py", REACH)
    robot = server.app.manager.get("demo-arm")
    async with server.client() as http:
        with robot.subscribe(kinds=[FaultReported, MotionStopped]) as events:
            with robot.subscribe(kinds=[TargetsSent]) as moving:
                assert (await attach(server, "reach.py")).status_code == 201
                await block_the_way(http, robot, moving)
            stopped = await next_event(events, lambda e: isinstance(e, MotionStopped))
            fault = await next_event(events, lambda e: isinstance(e, FaultReported))
    assert stopped.source == "script:reach.py" and "pillar" in stopped.blocked
    assert stopped.goals["Rotation"] == GOAL and HIT - 5.0 < stopped.joints["Rotation"] < HIT
    # It caught the stop and went on: its next move ran, then its last line failed.
    assert "reach.py, line 8: ScriptError: UNKNOWN_JOINT" in fault.message, fault.message
    await wait_for_no_master(server)
    assert robot.snapshot().joint("Rotation").goal == -10


async def test_a_remote_script_is_told_too(start_server: Any, tmp_path: Path) -> None:
    """`arena script` on another machine: its session counts the socket's `stopped`."""
    server = await start_server(demo=True)
    path = write(tmp_path, "reach.py", REACH)
    robot = server.app.manager.get("demo-arm")
    done: list[Any] = []

    async def run() -> None:
        done.append(await run_arena_script(server, path))

    with trio.fail_after(WAIT * 4):  # (a process of its own starts: generous)
        async with server.client() as http, trio.open_nursery() as nursery:
            with robot.subscribe(kinds=[TargetsSent]) as moving:
                nursery.start_soon(run)
                await block_the_way(http, robot, moving, timeout=WAIT * 4)
    out = done[0].stdout.decode()
    assert "stopped COLLISION" in out, (out, done[0].stderr.decode())
    assert "UNKNOWN_JOINT" in out + done[0].stderr.decode()
    assert robot.snapshot().joint("Rotation").goal == -10
    async with server.client() as http:
        assert "pillar" in (await http.get(ROBOT)).json()["last_stop"]["blocked"]


async def test_a_rest_move_waited_for_is_answered_when_it_ends(server: RunningServer) -> None:
    # `wait`: the answer is held until the arm is on its goals (`arrived`), until the guard
    # stops it on its way (COLLISION, 422, as the stop says), or until an e-stop (ESTOPPED,
    # 423); another command's goals, or the time running out, answer `arrived: false` and
    # why. Waits are for events: the pillar goes in once the arm is on its way.
    robot = server.app.manager.get("demo-arm")
    waited = {**SLOW, "wait": WAIT}
    async with server.client() as http:
        near = {"joints": [{"name": "Rotation", "value": 5.0}], "wait": WAIT}
        answer = await http.put(f"{ROBOT}/joints", json=near)
        assert answer.status_code == 200, answer.text
        assert answer.json()["arrived"] is True and answer.json()["status"] == "accepted"
        assert robot.snapshot().joints[0].virtual_value == 5.0  # there when answered

        answers: list[Any] = []

        async def put(body: dict[str, Any]) -> None:
            answers.append(await http.put(f"{ROBOT}/joints", json=body))

        async def stopped_on_the_way(then: Any) -> Any:
            answers.clear()
            with robot.subscribe(kinds=[TargetsSent]) as moving, trio.fail_after(WAIT):
                async with trio.open_nursery() as nursery:
                    nursery.start_soon(put, waited)
                    while not on_the_way(await moving.get()):
                        pass
                    await then()
            return answers[0]

        # the guard stops it
        answer = await stopped_on_the_way(lambda: put_pillar(http, robot))
        assert answer.status_code == 422, answer.text
        error = answer.json()["error"]
        assert error["code"] == "COLLISION" and "holds at Rotation" in error["message"], error
        await http.put(f"{ROBOT}/workspace", json={"keep_out": []})
        assert (await http.put(f"{ROBOT}/joints", json=near)).json()["arrived"] is True

        # an e-stop
        answer = await stopped_on_the_way(lambda: http.post(f"{ROBOT}/estop", json={}))
        assert answer.status_code == 423, answer.text
        assert answer.json()["error"]["code"] == "ESTOPPED", answer.text
        assert (await http.post(f"{ROBOT}/reset")).status_code == 200
        assert (await http.put(f"{ROBOT}/joints", json=near)).json()["arrived"] is True

        # another command
        back = {"joints": [{"name": "Rotation", "value": 0.0}]}
        answer = await stopped_on_the_way(lambda: http.put(f"{ROBOT}/joints", json=back))
        assert answer.status_code == 200, answer.text
        assert answer.json()["arrived"] is False and "another command" in answer.json()["why"]

        # the time (half a second of a move of seconds)
        answer = await http.put(f"{ROBOT}/joints", json={**SLOW, "wait": 0.5})
        assert answer.status_code == 200, answer.text
        assert answer.json() | {"arrived": False, "why": "not there after 0.5 s"} == answer.json()

        # a wait out of bounds is refused before anything moves
        answer = await http.put(f"{ROBOT}/joints", json={**SLOW, "wait": 1e6})
        assert answer.status_code == 422 and "wait" in answer.json()["error"]["message"]
