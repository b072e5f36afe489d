"""Robot groups: one master drives several robots, each with its own safety state."""

from __future__ import annotations

import json
from collections.abc import Awaitable, Callable

import pytest
import trio
import trio.testing
from trio_websocket import open_websocket_url

from arena.client import AsyncArena, MasterSession, Refused
from arena.protocol import messages as wire
from arena.protocol.errors import ArenaError, ErrorCode
from arena.robot.groups import GroupRegistry
from arena.robot.manager import RobotManager
from arena.robot.motion import Command
from arena.robot.safety import Mode
from tests.conftest import RunningServer, eventually
from tests.test_server_ws import receive

StartServer = Callable[..., Awaitable[RunningServer]]


async def three_arms(server: RunningServer, stop_together: bool = False) -> AsyncArena:
    arena = AsyncArena(server.url)
    for robot_id in ("left", "middle", "right"):
        await arena.create_robot(robot_id)
        await arena.attach_slave(robot_id, {"type": "mock-slave"})
    await arena.create_group("line", ["left", "middle", "right"], stop_together=stop_together)
    return arena


def goal(server: RunningServer, robot_id: str) -> float:
    return server.app.manager.get(robot_id).snapshot().joint("Rotation").goal


async def test_a_group_master_fans_out_and_an_estopped_member_stays_still(
    start_server: StartServer,
) -> None:
    server = await start_server()
    arena = await three_arms(server)
    async with MasterSession.open(server.url, "line") as master:
        ack = await master.command({"Rotation": 4})
        assert ack["data"]["status"] == "accepted"
        assert set(ack["data"]["members"]) == {"left", "middle", "right"}
        assert all(goal(server, r) == 4 for r in ("left", "middle", "right"))
        # Every member is mastered by the group's master.
        states = (await arena.group("line"))["states"]
        owners = {state["master"] for state in states.values()}
        assert len(owners) == 1 and owners.pop().startswith("ws-group-master")
        await arena.estop("middle", "a hand in the way")
        held = goal(server, "middle")  # (frozen where it was: on its way to 4 or there)
        assert 0 < held <= 4
        ack = await master.command({"Rotation": 6})
        assert ack["data"]["status"] == "partial"
        assert ack["data"]["members"]["middle"]["code"] == "ESTOPPED"
        assert (goal(server, "left"), goal(server, "middle"), goal(server, "right")) == (6, held, 6)
        await arena.reset("middle")
        assert (await master.command({"Rotation": 7}))["data"]["status"] == "accepted"
        assert goal(server, "middle") == 7
        described = await arena.estop_group("line", "end of shift")
        assert {state["state"] for state in described["states"].values()} == {"estopped"}
    await arena.aclose()


async def test_a_group_that_stops_together(start_server: StartServer) -> None:
    server = await start_server()
    arena = await three_arms(server, stop_together=True)
    async with MasterSession.open(server.url, "line") as master:
        await master.command({"Rotation": 2})
        await arena.estop("right", "bumper hit")
        with trio.fail_after(30):
            while True:
                states = (await arena.group("line"))["states"]
                if all(s["state"] == "estopped" for s in states.values()):
                    break
                await trio.sleep(0.02)
        assert "right" in states["left"]["estop_reason"]
        with pytest.raises(Refused):  # every member refused: the group's ack is `refused`
            await master.command({"Rotation": 3})
        await arena.reset_group("line")
        assert (await master.command({"Rotation": 3}))["data"]["status"] == "accepted"
    await arena.aclose()


async def test_group_claims_are_whole_or_nothing_and_bad_groups_are_refused(
    start_server: StartServer,
) -> None:
    server = await start_server()
    arena = await three_arms(server)
    async with server.client() as http:
        for body, code in [
            ({"id": "line", "members": ["left"]}, "GROUP_EXISTS"),
            ({"id": "left", "members": ["right"]}, "GROUP_EXISTS"),
            ({"id": "g", "members": ["left", "ghost"]}, "UNKNOWN_ROBOT"),
            ({"id": "g", "members": []}, "INVALID_BODY"),
            ({"id": "g", "members": ["left", "left"]}, "INVALID_BODY"),
            ({"id": "../g", "members": ["left"]}, "INVALID_BODY"),
        ]:
            answer = await http.post("/api/groups", json=body)
            assert answer.json()["error"]["code"] == code, body
        assert (await http.get("/api/groups/nope")).json()["error"]["code"] == "UNKNOWN_GROUP"
    # "right" already has a master: the group is refused and no member is left claimed.
    async with open_websocket_url(server.ws_url + "/ws/master/right") as holder:
        await receive(holder, "state")
        async with open_websocket_url(server.ws_url + "/ws/master/line") as group_master:
            refusal = json.loads(await group_master.get_message())
            assert refusal["data"]["code"] == "MASTER_ACTIVE"
        await eventually(lambda: server.app.manager.get("left").snapshot().owner is None)
        assert str(server.app.manager.get("left").snapshot().mode) == "idle"
    await arena.delete_group("line")
    assert (await arena.groups())["groups"] == []
    await arena.aclose()


async def test_deleting_a_member_leaves_the_group_master_with_the_rest(
    start_server: StartServer,
) -> None:
    server = await start_server()
    arena = await three_arms(server)
    async with open_websocket_url(server.ws_url + "/ws/master/line") as master:
        await receive(master, "state")
        await arena.delete_robot("left")
        left = await receive(master, "member_left")
        assert left["data"] == {"robot_id": "left", "reason": "robot deleted"}
        # Still attached to the others: its e-stop stops every remaining member.
        await master.send_message(json.dumps({"type": "estop", "data": {"reason": "hand"}}))
        with trio.fail_after(30):
            while {str(server.app.manager.get(r).snapshot().mode) for r in ("middle", "right")} != {
                "estopped"
            }:
                await receive(master, "state")
        await master.send_message(json.dumps({"type": "reset"}))
        with trio.fail_after(30):
            while "estopped" in {
                str(server.app.manager.get(r).snapshot().mode) for r in ("middle", "right")
            }:
                await receive(master, "state")
        command = {"type": "command", "data": {"joints": [{"name": "Rotation", "value": 5}]}}
        await master.send_message(json.dumps(command))
        ack = await receive(master, "ack")
        assert ack["data"]["status"] == "accepted" and set(ack["data"]["members"]) == {
            "middle",
            "right",
        }
        # The last members go: the group master is told each, then closed.
        await arena.delete_robot("middle")
        await arena.delete_robot("right")
        gone = {(await receive(master, "member_left"))["data"]["robot_id"] for _ in range(2)}
        assert gone == {"middle", "right"}
    await arena.aclose()


async def test_stop_together_watchers_survive_deletion_at_any_moment(
    autojump_clock: trio.testing.MockClock, manager: RobotManager
) -> None:
    for robot_id in ("a", "b", "c", "d"):
        await manager.create_robot("so-arm100", robot_id=robot_id)
    registry = GroupRegistry(manager)
    # Before: the robot is deleted before its watcher starts (the watcher is spawned, not run).
    group = registry.create("g", ["a", "b", "c", "d"], stop_together=True)
    await manager.delete("a")
    await trio.testing.wait_all_tasks_blocked()
    # During: deleted while its watcher waits on its events.
    await manager.delete("b")
    await trio.testing.wait_all_tasks_blocked()
    # After: a robot that has stopped hands a new observer a queue that has ended.
    stopped = await manager.create_robot("so-arm100", robot_id="gone")
    await manager.delete("gone")
    with stopped.subscribe() as events, pytest.raises(trio.EndOfChannel):
        await events.get()
    await registry._watch(group, "gone")  # returns at once, raises nothing
    # The group still stops together.
    await manager.get("c").estop("bumper")
    await trio.testing.wait_all_tasks_blocked()
    assert str(manager.get("d").snapshot().mode) == "estopped"
    registry.delete("g")


async def test_a_member_stopped_amid_a_flood_of_its_own_events_still_stops_the_group(
    autojump_clock: trio.testing.MockClock, manager: RobotManager
) -> None:
    """The watcher waits on state changes only: a burst of other events from the same robot
    (commands decided at once, each refused and published) cannot push its e-stop out of the
    watcher's bounded queue before the watcher has run."""
    for robot_id in ("a", "b"):
        await manager.create_robot("so-arm100", robot_id=robot_id)
    registry = GroupRegistry(manager)
    registry.create("g", ["a", "b"], stop_together=True)
    await trio.testing.wait_all_tasks_blocked()  # the watchers wait
    a = manager.get("a")
    assert a.estop_now("bumper hit") is not None  # no checkpoint from here to the flood's end
    results = a.command_run_now([Command.of({"Rotation": 1.0})] * 200)
    assert results is not None and not any(r.accepted for r in results)
    await trio.testing.wait_all_tasks_blocked()
    assert manager.get("b").snapshot().mode is Mode.ESTOPPED


def a_sentence(message: object) -> bool:
    """An error's message as a person reads it: capitalised (or opening on a quoted name), not
    shouted, ended by a full stop."""
    return (
        isinstance(message, str)
        and (message[:1].isupper() or message[:1] == "'")
        and not message.isupper()
        and message.endswith(".")
    )


async def test_a_group_describes_each_member_and_refuses_in_a_sentence_naming_the_id(
    autojump_clock: trio.testing.MockClock, manager: RobotManager
) -> None:
    for robot_id in ("a", "b", "c"):
        await manager.create_robot("so-arm100", robot_id=robot_id)
    registry = GroupRegistry(manager)
    group = registry.create("g", ["a", "b", "c"], stop_together=True)
    plain = registry.create("p", ["c"], stop_together=False)
    await manager.delete("b")
    await manager.get("c").estop("bumper hit")
    await trio.testing.wait_all_tasks_blocked()  # `g` stops together: `a` follows `c`
    a_reason = manager.get("a").snapshot().estop_reason
    assert a_reason is not None and "'c'" in a_reason
    assert group.describe(manager) == {
        "id": "g",
        "members": ["a", "b", "c"],
        "stopTogether": True,
        "states": {
            "a": {"state": "estopped", "master": None, "estop_reason": a_reason},
            "b": {"state": "deleted"},
            "c": {"state": "estopped", "master": None, "estop_reason": "bumper hit"},
        },
    }
    assert plain.describe(manager)["stopTogether"] is False
    refusals = [
        (lambda: registry.get("nope"), ErrorCode.UNKNOWN_GROUP, "'nope'"),
        (lambda: registry.create("g", ["a"], False), ErrorCode.GROUP_EXISTS, "'g'"),
        (lambda: registry.create("a", ["c"], False), ErrorCode.GROUP_EXISTS, "'a'"),
        (lambda: registry.create("h", [], False), ErrorCode.INVALID_BODY, ""),
        (lambda: registry.create("h", ["a", "a"], False), ErrorCode.INVALID_BODY, ""),
    ]
    for refused, code, names in refusals:
        with pytest.raises(ArenaError) as info:
            refused()
        assert info.value.code is code
        assert a_sentence(info.value.message) and names in info.value.message
    assert [g.group_id for g in registry.all()] == ["g", "p"]  # the refusals changed nothing


def test_a_group_ack_says_how_the_group_answered_in_the_contracts_shape() -> None:
    accepted = wire.AckData("accepted")
    clamped = wire.AckData("clamped", None, "limited", [wire.ClampInfo("Rotation", 200.0, 180.0)])
    refused = wire.AckData("refused", "ESTOPPED", "stopped")
    cases = [
        (accepted, accepted, "accepted"),
        (accepted, clamped, "clamped"),
        (clamped, refused, "partial"),
        (refused, refused, "refused"),
    ]
    for first, second, expected in cases:
        assert wire.GroupAckData.of({"a": first, "b": second}).status == expected
    # Each member's ack data whole, as the group master always sent it.
    data = wire.GroupAckData.of({"a": accepted, "b": refused})
    text = wire.encode(wire.GroupAckMessage(timestamp="2026-01-01T00:00:00.000Z", data=data))
    assert json.loads(text) == {
        "type": "ack",
        "timestamp": "2026-01-01T00:00:00.000Z",
        "data": {
            "status": "partial",
            "members": {
                "a": {"status": "accepted", "code": None, "message": "", "clamped": []},
                "b": {"status": "refused", "code": "ESTOPPED", "message": "stopped", "clamped": []},
            },
        },
    }
