"""A policy on another machine (`arena policy --url`) as a robot's master: it drives over the
public API, each inference it runs is recorded on the server as a local worker's is, camera
frames leave the server at the policy's input size, and the server's watchdog trips when its
commands stop coming (a stalled link or worker), as it does for a policy it runs itself.

The watchdog's timing is checked on trio's mock clock (`autojump_clock`); the end-to-end
tests wait for events."""

from __future__ import annotations

import json
import math
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest
import trio
import trio.testing
from trio.testing import MockClock
from trio_websocket import open_websocket_url

from arena.protocol import messages as wire
from arena.protocol.errors import ArenaError, ErrorCode, Severity
from arena.recording.mcap_file import read_recording
from arena.robot.events import CommandHandled, FaultReported, PolicyInferred
from arena.server.ws.remote_policy import LINK_ALLOWANCE, RemotePolicy
from tests.conftest import RunningServer
from tests.test_cameras import TEST_CAMERA, jpeg_rgb
from tests.test_policy_server import (
    ROBOT,
    WAIT,
    Start,
    checkpoint,
    next_event,
    ready,
    tiny,  # noqa: F401  (the fixture)
    workers,
)
from tests.test_server_ws import receive

# -- the watchdog, on the mock clock -----------------------------------------------------------


class FakeLink:
    master_id = "policy:act:remote"

    def __init__(self) -> None:
        self.detached = trio.Event()


class FakeRobot:
    """What `RemotePolicy` uses of a robot: its id and where faults and inferences go."""

    robot_id = "arm"

    def __init__(self) -> None:
        self.faults: list[tuple[str, str, str, Severity, float]] = []
        self.inferences: list[PolicyInferred] = []
        self.paused = False

    def snapshot(self) -> SimpleNamespace:
        master = SimpleNamespace(peer_id=FakeLink.master_id, paused=self.paused)
        return SimpleNamespace(master=master, paused_master=None)

    def report_sensor_fault(self, source: str, code: str, message: str, sev: Severity) -> None:
        self.faults.append((source, code, message, sev, trio.current_time()))

    def report_inference(self, event: PolicyInferred) -> None:
        self.inferences.append(event)


def remote_policy() -> tuple[RemotePolicy, FakeRobot, FakeLink]:
    robot, link = FakeRobot(), FakeLink()
    return RemotePolicy(robot, link), robot, link  # type: ignore[arg-type]


async def test_the_watchdog_trips_once_a_silence_and_never_while_commands_flow(
    autojump_clock: MockClock,
) -> None:
    policy, robot, link = remote_policy()
    async with trio.open_nursery() as nursery:
        policy.declare(wire.PolicyData(fps=30, stall_periods=2), nursery)
        window = 2 / 30 + LINK_ALLOWANCE
        assert policy.window == pytest.approx(window)
        # Declared but not commanding yet (loading, the first inference): no stall.
        await trio.sleep(10)
        assert robot.faults == []
        # Commands at 30 Hz, and late ones just inside the window: no stall.
        for _ in range(90):
            policy.commanded()
            await trio.sleep(1 / 30)
        for _ in range(5):
            policy.commanded()
            await trio.sleep(window * 0.95)
        assert robot.faults == []
        # Then silence: one fault, one window after the last command, naming the master.
        policy.commanded()
        last = trio.current_time()
        await trio.sleep(5)
        assert len(robot.faults) == 1
        source, code, message, severity, at = robot.faults[0]
        assert (source, code, severity) == (link.master_id, "POLICY_STALLED", Severity.WARNING)
        assert at == pytest.approx(last + window) and "holds" in message
        # The next command arms it again: a second silence is a second fault.
        policy.commanded()
        await trio.sleep(5)
        assert len(robot.faults) == 2 and policy.stalls == 2
        # Paused by the robot (POST .../master/pause): its silence is no stall.
        robot.paused = True
        policy.commanded()
        await trio.sleep(5)
        assert len(robot.faults) == 2
        robot.paused = False
        policy.commanded()  # resumed, commanding again, then silent: a stall again
        await trio.sleep(5)
        assert len(robot.faults) == 3
        link.detached.set()
        policy.commanded()
        await trio.sleep(5)
        assert len(robot.faults) == 3  # a link the robot let go is watched no more
        nursery.cancel_scope.cancel()


async def test_inference_records_are_bounded_by_the_policys_rate(
    autojump_clock: MockClock,
) -> None:
    policy, robot, _ = remote_policy()
    record = wire.InferenceData(
        timestep=3, chunk_size=10, kept=7, latency=0.2, inference=0.1, frame_age=0.05
    )
    with pytest.raises(ArenaError) as undeclared:
        policy.inferred(record)
    assert undeclared.value.code is ErrorCode.INVALID_MESSAGE
    async with trio.open_nursery() as nursery:
        policy.declare(wire.PolicyData(fps=10), nursery)
        with pytest.raises(ArenaError) as twice:
            policy.declare(wire.PolicyData(fps=10), nursery)
        assert twice.value.code is ErrorCode.INVALID_MESSAGE
        refused = 0
        for _ in range(1000):  # a flood, all at once
            try:
                policy.inferred(record)
            except ArenaError as error:
                assert error.code is ErrorCode.RATE_LIMITED
                refused += 1
        assert len(robot.inferences) == 10 and refused == 990 and policy.dropped == 990
        await trio.sleep(1)  # a second later, another second's worth (fps 10)
        for _ in range(20):
            try:
                policy.inferred(record)
            except ArenaError:
                refused += 1
        assert len(robot.inferences) == 20 and refused == 1000
        event = robot.inferences[0]
        assert (event.policy, event.timestep, event.kept, event.frame_age) == (
            "policy:act:remote",
            3,
            7,
            0.05,
        )
        nursery.cancel_scope.cancel()


# -- the messages and the frame endpoint through a real server ---------------------------------


async def test_a_master_declares_its_policy_and_bad_records_are_refused(
    server: RunningServer,
) -> None:
    url = f"{server.ws_url}/ws/master/demo-arm?id=remote-policy"
    with server.app.manager.get("demo-arm").subscribe(kinds=[PolicyInferred]) as events:
        async with open_websocket_url(url) as ws:
            await receive(ws, "state")
            record = {"timestep": 1, "chunk_size": 10, "kept": 10, "latency": 0.3, "inference": 0.2}
            await ws.send_message(json.dumps({"type": "inference", "data": record}))
            error = (await receive(ws, "error"))["data"]
            assert error["code"] == "INVALID_MESSAGE" and "policy" in error["message"]
            await ws.send_message(json.dumps({"type": "policy", "data": {"fps": 0}}))
            assert (await receive(ws, "error"))["data"]["code"] == "INVALID_MESSAGE"
            await ws.send_message(json.dumps({"type": "policy", "data": {"fps": 30}}))
            assert (await receive(ws, "ack"))["data"]["status"] == "accepted"
            for bad in ({"latency": -1}, {"latency": math.inf}, {"kept": "7"}, {"extra": 1}):
                text = json.dumps({"type": "inference", "data": {**record, **bad}})
                await ws.send_message(text)
                code = (await receive(ws, "error"))["data"]["code"]
                assert code in ("INVALID_MESSAGE", "UNKNOWN_FIELD", "INVALID_JSON"), (bad, code)
            await ws.send_message(json.dumps({"type": "inference", "data": record}))
            with trio.fail_after(WAIT):
                event = await events.get()
    assert isinstance(event, PolicyInferred)
    assert (event.policy, event.timestep, event.latency) == ("remote-policy", 1, 0.3)
    assert event.frame_age is None


async def test_a_frame_is_scaled_to_the_size_asked_before_it_leaves(server: RunningServer) -> None:
    base = "/api/robots/demo-arm/cameras"
    async with server.client() as http:
        assert (await http.post(base, json=TEST_CAMERA)).status_code == 201
        whole = await http.get(f"{base}/front/frame")
        small = await http.get(f"{base}/front/frame", params={"width": 96, "height": 96})
        assert small.status_code == 200, small.text
        assert jpeg_rgb(whole.content).shape == (240, 320, 3)
        assert jpeg_rgb(small.content).shape == (96, 96, 3)
        assert len(small.content) < len(whole.content)
        same = await http.get(f"{base}/front/frame", params={"width": 320, "height": 240})
        assert jpeg_rgb(same.content).shape == (240, 320, 3)
        for params in (
            {"width": 96},
            {"width": 95, "height": 96},
            {"width": 0, "height": 96},
            {"width": 99999, "height": 96},
            {"width": "ninety", "height": 96},
            {"width": "²", "height": 96},
        ):
            refused = await http.get(f"{base}/front/frame", params=params)
            assert refused.status_code == 422, params
            assert refused.json()["error"]["code"] == "INVALID_VALUE"


async def test_a_remote_policy_that_stops_commanding_is_reported_stalled(
    server: RunningServer,
) -> None:
    """What a stalled link looks like from the server: a policy master that commanded, then
    nothing. (The timing of the window is the mock-clock test's.)"""
    robot = server.app.manager.get("demo-arm")
    url = f"{server.ws_url}/ws/master/demo-arm?id=remote-policy"
    with robot.subscribe(kinds=[FaultReported]) as events:
        async with open_websocket_url(url) as ws:
            await receive(ws, "state")
            await ws.send_message(json.dumps({"type": "policy", "data": {"fps": 30}}))
            await receive(ws, "ack")
            command = {"joints": [{"name": "Rotation", "value": 1.0}]}
            await ws.send_message(json.dumps({"type": "command", "data": command}))
            fault = await next_event(
                events, lambda e: isinstance(e, FaultReported) and e.code == "POLICY_STALLED"
            )
    assert fault.peer_id == "remote-policy" and fault.severity == Severity.WARNING


# -- end to end, with a real policy ------------------------------------------------------------


async def test_arena_policy_drives_over_the_public_api_and_the_server_records_it(
    start_server: Start,
    tiny: Path,  # noqa: F811
) -> None:
    from arena.policy.master import PolicySettings
    from arena.policy.remote import run_remote

    server = await start_server(demo=True)
    robot = await ready(server, camera=False)
    async with server.client() as http:  # a 320 x 240 camera; the policy takes 32 x 32
        answer = await http.post(f"{ROBOT}/cameras", json=TEST_CAMERA)
        assert answer.status_code == 201, answer.text
        whole = len((await http.get(f"{ROBOT}/cameras/front/frame")).content)
    identity = f"policy:act:{checkpoint(tiny)}"
    done = trio.Event()
    ran: list[Any] = []

    async def remote() -> None:
        ran.append(await run_remote(PolicySettings(tiny, task="wave"), server.url, "demo-arm"))
        done.set()

    with robot.subscribe(kinds=[CommandHandled, PolicyInferred]) as events:
        async with trio.open_nursery() as nursery:
            nursery.start_soon(remote)
            for _ in range(10):
                command = await next_event(events, lambda e: isinstance(e, CommandHandled))
                assert command.source == identity and command.result.accepted
            for _ in range(2):
                await next_event(events, lambda e: isinstance(e, PolicyInferred))
            assert robot.snapshot().master.peer_id == identity
            async with server.client() as http:
                await http.post(f"{ROBOT}/estop", json={"reason": "test"})
            with trio.fail_after(WAIT):
                await done.wait()
    run = ran[0]
    assert run.master.counters.sent >= 10 and workers() == []
    # Frames came at the policy's size: a 32 x 32 JPEG is a small part of a 320 x 240 one.
    assert run.frames > 0 and run.frame_bytes / run.frames < whole / 2
    async with server.client() as http:
        stopped = (await http.post("/api/recordings/current/stop")).json()["stopped"]
    recording = read_recording(Path(server.app.recorder.folder) / stopped)
    inferences = [m.data for m in recording.messages if m.topic == "/robots/demo-arm/policy"]
    assert len(inferences) >= 2
    for data in inferences:
        assert data["policy"] == identity and data["chunk_size"] == 10
        assert 0 < data["inference"] <= data["latency"] < WAIT
        assert data["frame_age"] is not None and data["frame_age"] >= 0
    steps = [data["timestep"] for data in inferences]
    assert steps == sorted(steps)
