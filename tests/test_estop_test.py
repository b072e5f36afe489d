"""`arena estop-test`: the analysis on made-up evidence, the live test against a real server
(mock slave and the simulated servo bus, both stop policies), and the check of a recording."""

from __future__ import annotations

import json
from collections.abc import Awaitable, Callable, Iterator
from pathlib import Path

import pytest
import trio
from trio.testing import MockClock
from trio_websocket import open_websocket_url

from arena import cli
from arena.estop_test import analysis, live
from arena.estop_test.analysis import (
    Trial,
    breaches,
    joint_stops,
    load_limits,
    percentile,
    recorded_stops,
    stop_trial,
    summarize,
)
from arena.estop_test.live import PATHS, Settings, run
from arena.recording.mcap_file import RecordedMessage, read_recording
from arena.robot import core
from arena.robot.safety import Allowed, Event, MasterCommand, Mode, Outcome, SafetyState
from arena.servo.sim_pty import PtySimBus
from tests.conftest import RunningServer
from tests.hardware import running_sim, servo_torque
from tests.scenarios import record_scenario
from tests.test_recording import session_scenario

StartServer = Callable[..., Awaitable[RunningServer]]


def decelerating(trigger: float = 1.0) -> list[tuple[float, dict[str, float]]]:
    """A joint at 10 deg moving up at 100 deg/s until 0.05 s after the trigger, then braking
    over 0.05 s with a 0.3 deg overshoot that settles back; another joint that never moves."""
    samples = [(trigger - 0.02, {"a": 8.0, "b": 1.0}), (trigger, {"a": 10.0, "b": 1.0})]
    samples += [
        (trigger + 0.02, {"a": 12.0, "b": 1.0}),
        (trigger + 0.05, {"a": 15.0, "b": 1.0}),
        (trigger + 0.08, {"a": 15.8, "b": 1.0}),
        (trigger + 0.10, {"a": 15.5, "b": 1.0}),
        (trigger + 0.12, {"a": 15.45, "b": 1.0}),
    ]
    return samples


def test_stopping_time_and_distance_from_joint_samples() -> None:
    stops = joint_stops(decelerating(), 1.0, threshold=0.1, until=2.0)
    # a: last outside 0.1 deg of the final 15.45 is 15.8 at +0.08; at rest from +0.10
    assert stops["a"].time_ms == pytest.approx(100.0)
    assert stops["a"].distance_deg == pytest.approx(5.8)  # overshoot counts
    assert stops["a"].at_rest
    assert stops["b"].time_ms == 0.0 and stops["b"].distance_deg == 0.0
    # watched too briefly after rest: still counts as moving
    assert not joint_stops(decelerating(), 1.0, threshold=0.1, until=1.15)["a"].at_rest


def test_a_trial_says_what_went_out_and_moved_after_the_stop() -> None:
    trial = stop_trial(
        "rest",
        1.0,
        estopped=1.004,
        notice=1.003,
        targets=[0.98, 0.99, 1.001, 1.002],
        samples=decelerating(),
        threshold=0.1,
        until=2.0,
    )
    assert trial.estopped_ms == pytest.approx(4.0)
    assert trial.stop_notice_ms == pytest.approx(3.0)
    assert trial.last_target_ms == pytest.approx(2.0)
    assert trial.sent_after_stop == 0 and not trial.moved_after_stop and trial.error is None
    assert trial.stopping_time_ms == pytest.approx(100.0)
    assert trial.trace[-1] == (pytest.approx(1.0), {"a": 15.45, "b": 1.0})  # held to the end
    late = stop_trial(
        "rest",
        1.0,
        estopped=1.004,
        notice=1.003,
        targets=[1.002, 1.5],
        samples=decelerating(),
        threshold=0.1,
        until=2.0,
    )
    assert late.sent_after_stop == 1 and late.moved_after_stop
    never = stop_trial(
        "heartbeat", 1.0, estopped=None, notice=None, targets=[], samples=[], threshold=0.1,
        until=2.0,
    )  # fmt: skip
    assert never.error is not None and "never" in never.error


def test_percentiles_limits_and_breaches(tmp_path: Path) -> None:
    assert percentile([5.0, 1.0, 3.0, 2.0, 4.0], 50) == 3.0
    assert percentile([float(v) for v in range(1, 101)], 99) == 99.0
    trials = [Trial("rest", estopped_ms=v, stop_notice_ms=v - 0.5) for v in (2.0, 3.0, 9.0)]
    assert summarize(trials)["estopped_ms"] == {"p50": 3.0, "p99": 9.0, "max": 9.0}
    limits_file = tmp_path / "limits.toml"
    limits_file.write_text(
        '["*"]\n"estopped_ms.p99" = 10\n"stop_notice_ms.max" = 100\n'
        '[rest]\n"estopped_ms.p50" = 2.5\n'
    )
    limits = load_limits(limits_file)
    found = breaches("rest", trials, limits)
    assert [(b.what, b.value, b.limit) for b in found] == [("estopped_ms.p50", 3.0, 2.5)]
    assert breaches("global", trials, limits) == []  # only the "*" limits, all met
    trials.append(Trial("rest", estopped_ms=1.0, sent_after_stop=2))
    assert any(b.what == "moved_after_stop" for b in breaches("global", trials, {}))
    for bad in ('[rest]\n"speed.p50" = 1\n', '[rest]\n"estopped_ms.p42" = 1\n', "x = 1\n"):
        limits_file.write_text(bad)
        with pytest.raises(ValueError):
            load_limits(limits_file)


async def test_every_stop_path_against_the_mock_slave(
    start_server: StartServer, tmp_path: Path
) -> None:
    # A heartbeat timeout long enough that a loaded machine never drops the tester's own
    # masters (their heartbeats come every timeout / 4), short enough for the silent path.
    server = await start_server(demo=True, heartbeat_timeout=3.0, heartbeat_interval=0.5)
    # `settle` and `timeout` are only bounds: each trial goes on once the stop is seen and the
    # arm is at rest
    settings = Settings(
        url=server.url, robot="demo-arm", trials=1, settle=30.0, lead=0.3, timeout=30.0
    )
    results, notes = await trio.to_thread.run_sync(run, settings)
    assert list(results) == list(PATHS) and notes == []  # heartbeat too: the server is quick
    for path, trials in results.items():
        for trial in trials:
            assert trial.error is None, (path, trial.error)
            assert trial.estopped_ms is not None and trial.stop_notice_ms is not None
            assert trial.sent_after_stop == 0 and not trial.moved_after_stop, path
            assert set(trial.joints) >= {"Rotation"}
    # a silent master is dropped only after the server's heartbeat timeout (3 s)
    (silent,) = results["heartbeat"]
    assert silent.estopped_ms is not None and silent.estopped_ms > 2900
    async with server.client() as http:
        assert (await http.get("/api/groups")).json()["groups"] == []  # its group is gone
        status = (await http.get("/api/robots/demo-arm/status")).json()
        assert status["state"] != "estopped"  # left reset


async def test_the_command_line_writes_json_and_fails_on_a_breach(
    start_server: StartServer, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    server = await start_server(demo=True)
    limits = tmp_path / "limits.toml"
    limits.write_text('["*"]\n"estopped_ms.max" = 0.001\n')  # nothing stops that fast
    output = tmp_path / "stops.json"
    args = ["estop-test", "--url", server.url, "--robot", "demo-arm", "--trials", "2"]
    args += ["--paths", "rest,master-message", "--settle", "30", "--json", str(output)]
    code = await trio.to_thread.run_sync(cli.main, [*args, "--limits", str(limits)])
    printed = capsys.readouterr().out
    assert code == 1 and "BREACH rest: estopped_ms.max" in printed
    assert "note: heartbeat left out" not in printed  # only when every path is asked for
    report = json.loads(output.read_text())
    assert set(report["paths"]) == {"rest", "master-message"} and not report["passed"]
    for entry in report["paths"].values():
        assert len(entry["trials"]) == 2 and entry["moved_after_stop"] is False
        assert set(entry["summary"]["estopped_ms"]) == {"p50", "p99", "max"}
    wrong = await trio.to_thread.run_sync(
        cli.main, ["estop-test", "--url", server.url, "--robot", "nobody"]
    )
    assert wrong == 2 and "nobody" in capsys.readouterr().err


@pytest.fixture
def sim(tmp_path: Path) -> Iterator[PtySimBus]:
    yield from running_sim(tmp_path)


@pytest.mark.parametrize("policy", ["hold", "torque-off"])
async def test_both_stop_policies_on_the_simulated_bus(
    start_server: StartServer, sim: PtySimBus, policy: str
) -> None:
    server = await start_server()
    async with server.client() as http:
        made = await http.post("/api/robots", json={"id": "arm", "robot_type": "so-arm100"})
        assert made.status_code == 201
        slave = {"type": "usb-slave", "port": str(sim.link), "estop": policy}
        assert (await http.post("/api/robots/arm/slaves", json=slave)).status_code == 201
    torque_after_stop: list[dict[int, int]] = []

    def test_and_look() -> tuple[dict[str, list[Trial]], list[str]]:
        settings = Settings(
            url=server.url,
            robot="arm",
            trials=2,
            paths=("master-message",),
            settle=30.0,
            timeout=30.0,
        )
        return run(settings)

    results, _ = await trio.to_thread.run_sync(test_and_look)
    (trials,) = results.values()
    for trial in trials:
        assert trial.error is None and not trial.moved_after_stop
        # the servos' own positions came back from the bus and were seen coming to rest
        assert trial.joints["Rotation"].at_rest and trial.stopping_distance_deg is not None
    async with server.client() as http:
        await http.post("/api/robots/arm/estop", json={"reason": "look at the servos"})
        reply = await http.get("/api/robots/arm/status")
        assert reply.json()["state"] == "estopped"
    deadline = trio.current_time() + 30  # the slave applies the policy on its next bus job
    while trio.current_time() < deadline:
        torque_after_stop.append(servo_torque(sim))
        if set(torque_after_stop[-1].values()) == ({0} if policy == "torque-off" else {1}):
            break
        await trio.sleep(0.02)
    assert set(torque_after_stop[-1].values()) == ({0} if policy == "torque-off" else {1})


async def test_a_recording_is_checked_for_motion_after_each_stop(
    autojump_clock: MockClock, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (path,) = await record_scenario(tmp_path, session_scenario)
    recording = read_recording(path)
    found = recorded_stops(recording.messages, threshold=0.5)
    (stops,) = found.values()
    (stop,) = stops
    assert stop.path == "arm: test stop" and stop.estopped_ms == 0.0
    assert stop.sent_after_stop == 0 and not stop.moved_after_stop
    assert cli.main(["estop-test", "--offline", str(path)]) == 0
    assert "arm: test stop" in capsys.readouterr().out
    # the same stop with a target slipped in after it is caught
    estop = next(
        m for m in recording.messages if m.kind == "state" and m.data["mode"] == "estopped"
    )
    t = float(estop.data["t"]) + 0.1
    forged = RecordedMessage(
        f"/robots/{estop.robot_id}/targets",
        estop.robot_id,
        "targets",
        estop.log_time + 100_000_000,
        {"t": t, "joints": {"Rotation": 1.0}},
    )
    index = recording.messages.index(estop) + 1
    messages = [*recording.messages[:index], forged, *recording.messages[index:]]
    (caught,) = recorded_stops(messages, threshold=0.5)["arm"]
    assert caught.sent_after_stop == 1 and caught.moved_after_stop


async def test_only_the_robot_under_test_is_stopped_unless_global_is_named(
    start_server: StartServer, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    server = await start_server(demo=True)
    async with server.client() as http:
        assert (await http.post("/api/robots", json={"id": "bystander"})).status_code == 201
        slave = await http.post("/api/robots/bystander/slaves", json={"type": "mock-slave"})
        assert slave.status_code == 201
    bystander = server.app.manager.get("bystander")
    output = tmp_path / "stops.json"
    args = ["estop-test", "--url", server.url, "--robot", "demo-arm", "--trials", "1"]
    args += ["--settle", "30", "--json", str(output)]
    assert await trio.to_thread.run_sync(cli.main, args) == 0
    printed = capsys.readouterr().out
    assert "note: global skipped" in printed
    assert "1 besides 'demo-arm' (bystander)" in printed
    report = json.loads(output.read_text())
    assert "global" not in report["paths"] and {"rest", "group"} <= set(report["paths"])
    assert any(note.startswith("global skipped") for note in report["notes"])
    assert bystander.estop_count == 0 and str(bystander.snapshot().mode) == "idle"
    # Named, it runs, and it does what it says: every robot stops.
    results, notes = await trio.to_thread.run_sync(
        run, Settings(url=server.url, robot="demo-arm", trials=1, paths=("global",), settle=30.0)
    )
    assert list(results) == ["global"] and results["global"][0].error is None and notes == []
    assert bystander.estop_count == 1


def joint_states(pose: dict[str, float]) -> str:
    data = [{"name": name, "value": round(value, 3)} for name, value in pose.items()]
    return json.dumps({"type": "joint_states", "data": data})


async def runaway_slave(url: str) -> None:
    """A WebSocket slave that follows its targets until it is told to stop, then keeps
    moving (a joint shaking 3 degrees either way, every report 6 degrees from the last, so
    that no two are ever within the tool's threshold of each other): an arm whose stop does
    not work."""
    async with open_websocket_url(url) as ws:
        pose = {"Rotation": 0.0}
        await ws.send_message(joint_states(pose))
        while True:
            message = json.loads(await ws.get_message())
            if message["type"] == "execute_command":
                pose = {j["name"]: j["value"] for j in message["data"]["joints"]}
                await ws.send_message(joint_states(pose))
            elif message["type"] == "estop":
                break
        for k in range(100_000):  # until the test ends: every 20 ms, never still
            swing = {name: value + (3.0 if k % 2 else -3.0) for name, value in pose.items()}
            await ws.send_message(joint_states(swing))
            await trio.sleep(0.02)


async def still_slave(url: str) -> None:
    """A WebSocket slave that says where it is once and never moves."""
    async with open_websocket_url(url) as ws:
        await ws.send_message(joint_states({"Rotation": 0.0}))
        while True:
            await ws.get_message()


def lenient_after_an_estop(monkeypatch: pytest.MonkeyPatch) -> None:
    """The server made to misbehave: an e-stopped robot goes on taking its master's commands
    (and sending their targets to its slaves)."""
    strict = core.transition

    def transition(state: SafetyState, event: Event) -> Outcome:
        if isinstance(event, MasterCommand) and state.mode is Mode.ESTOPPED:
            return Allowed(state)
        return strict(state, event)

    monkeypatch.setattr(core, "transition", transition)


@pytest.mark.parametrize("fault", ["a slave that keeps moving", "a server that keeps sending"])
async def test_the_tool_catches_motion_after_a_stop_and_exits_1(
    start_server: StartServer,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
    fault: str,
) -> None:
    server = await start_server()
    async with server.client() as http:
        made = await http.post("/api/robots", json={"id": "arm", "robot_type": "so-arm100"})
        assert made.status_code == 201
    slave = runaway_slave if fault == "a slave that keeps moving" else still_slave
    if fault == "a server that keeps sending":
        lenient_after_an_estop(monkeypatch)
    # The tool takes silence after the stop for rest once it has lasted STILL_FOR (0.2 s): on a
    # loaded machine the first report of a runaway slave, or the first command a lenient
    # server lets through, can come later than that, and so can a gap between two of the
    # runaway's reports (a joint is at rest once it has kept still that long). Three seconds
    # here, for both (the tool's wait and the analysis of each joint), within a settle of six.
    monkeypatch.setattr(live, "STILL_FOR", 3.0)
    monkeypatch.setattr(analysis, "STILL_FOR", 3.0)
    output = tmp_path / "stops.json"
    args = ["estop-test", "--url", server.url, "--robot", "arm", "--trials", "1"]
    args += ["--paths", "rest", "--settle", "6", "--json", str(output)]
    async with trio.open_nursery() as nursery:
        nursery.start_soon(slave, server.ws_url + "/ws/slave/arm?id=arm-under-test")
        code = await trio.to_thread.run_sync(cli.main, args)
        nursery.cancel_scope.cancel()
    printed = capsys.readouterr().out
    assert code == 1 and "BREACH rest: moved_after_stop: in 1 of 1 trials" in printed
    (trial,) = json.loads(output.read_text())["paths"]["rest"]["trials"]
    assert trial["moved_after_stop"] and trial["error"] is None
    if fault == "a slave that keeps moving":  # seen in the joints it reports
        assert trial["sent_after_stop"] == 0 and not trial["joints"]["Rotation"]["at_rest"]
    else:  # seen in the targets the tool's own slave got after its stop notice
        assert trial["sent_after_stop"] > 0
        assert all(joint["at_rest"] for joint in trial["joints"].values())
