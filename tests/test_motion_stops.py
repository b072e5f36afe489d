"""A move the collision guard stops after it was accepted is told to whoever commanded it."""

from __future__ import annotations

import json

import trio
from trio_websocket import open_websocket_url

from arena.protocol.errors import ErrorCode, Severity
from arena.robot.events import FaultReported
from arena.robot.workspace import Box, Workspace
from tests.conftest import RunningServer

#: A keep-out box around the whole arm: every pose from now on would be inside it.
EVERYWHERE = Box("wall", (-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))


async def test_a_master_is_told_when_its_accepted_move_is_stopped_on_the_way(
    server: RunningServer,
) -> None:
    robot = await server.app.manager.create_robot("so-arm100", robot_id="guarded")
    with robot.subscribe(kinds=[FaultReported], maxlen=64) as faults:
        async with open_websocket_url(server.ws_url + "/ws/master/guarded?id=alice") as master:
            command = {"type": "command", "data": {"joints": [{"name": "Rotation", "value": 90}]}}
            await master.send_message(json.dumps(command))
            answer: dict = {}
            with trio.fail_after(30):
                while answer.get("type") != "ack":
                    answer = json.loads(await master.get_message())
            assert answer["data"]["status"] == "accepted"
            # A keep-out box set while the arm is on its way (two seconds at most): the next
            # target would be inside it, so the motion stops there.
            await robot.set_workspace(Workspace(floor=0.0, keep_out=(EVERYWHERE,)))
            with trio.fail_after(30):
                while True:
                    message = json.loads(await master.get_message())
                    if message["type"] == "error":
                        break
            assert message["data"]["code"] == "COLLISION"
            assert message["data"]["severity"] == "warning"
            assert "wall" in message["data"]["message"]
        assert robot.core.collision_stops == 1
        assert not robot.core.motion.moving
        assert robot.core.motion.positions["Rotation"] < 90.0
        reported = [faults.get_nowait() for _ in range(len(faults))]
    stops = [f for f in reported if f.code == ErrorCode.COLLISION]
    assert len(stops) == 1
    assert stops[0].peer_id == "alice" and stops[0].severity is Severity.WARNING
    assert "wall" in stops[0].message


async def test_manual_control_is_told_by_a_recorded_fault(server: RunningServer) -> None:
    robot = await server.app.manager.create_robot("so-arm100", robot_id="manual")
    with robot.subscribe(kinds=[FaultReported], maxlen=64) as faults:
        async with server.client() as http:
            answer = await http.put(
                "/api/robots/manual/joints", json={"joints": [{"name": "Rotation", "value": 90}]}
            )
            assert answer.json()["status"] == "accepted"
        await robot.set_workspace(Workspace(floor=0.0, keep_out=(EVERYWHERE,)))
        with trio.fail_after(30):
            while not len(faults):
                await trio.sleep(0.01)
        fault = faults.get_nowait()
    assert fault.code == ErrorCode.COLLISION and fault.peer_id == "manual"
    assert robot.core.collision_stops == 1
