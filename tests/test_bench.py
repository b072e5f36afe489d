"""The benchmark scenarios run end to end (tiny sizes). Nothing about speed is asserted here."""

from __future__ import annotations

import asyncio
import json
import math
import re
import select
import socket
import struct
import subprocess
import sys
import threading

import httpx
import pytest

from arena import bench
from arena.bench.camera import camera
from arena.bench.client import BlockingHttp, BlockingWebSocket, masked_frame
from arena.bench.common import (
    EXECUTE_MARK,
    attached_slave,
    command_text,
    create_bench_robot,
    process_cpu_seconds,
    time_to,
    wait_for_slaves,
)
from arena.bench.policy import observation_to_command
from arena.protocol.ws_frames import OP_CLOSE, OP_TEXT, accept_key, encode_frame
from arena.recording.mcap_file import RecordedMessage
from tests.conftest import need


def test_bench_scenarios_run_against_a_real_server() -> None:
    async def scenarios() -> dict[str, float]:
        async with bench.running_server() as server:
            results = await bench.relay(server, count=20)
            results.update(await bench.throughput(server, count=200))
            results.update(await bench.estop(server, trials=3, robots=3))
            results.update(
                await bench.fleet(server, robots=2, rate=20, seconds=0.5, heartbeat_period=0.2)
            )
            return results

    results = asyncio.run(scenarios())
    assert results["throughput_refused"] == 0
    assert results["throughput_reached_slave"] >= 1
    assert results["fleet_messages"] > 0
    assert results["fleet_heartbeats_sent"] >= 4  # one every 0.1 s, each slave in turn
    assert results["fleet_commands_unacknowledged"] == 0
    for key in (
        "relay_p50_us",
        "relay_deaf_p99_us",
        "throughput_accepted_per_s",
        "estop_one_p50_ms",
        "estop_one_answered_p99_ms",
        "estop_one_httpx_p50_ms",
        "estop_one_websocket_p99_ms",
        "estop_all_median_ms",
        "fleet_p99_us",
    ):
        assert results[key] > 0, key


def test_the_flood_scenario_measures_an_estop_while_a_viewer_floods_pings() -> None:
    async def flooded() -> dict[str, float]:
        async with bench.running_server(record=False) as server:
            return await bench.flood(server, trials=5)

    results = asyncio.run(flooded())
    # Answered at all (a server the flood froze reads infinity), and memory stayed bounded
    # (the server used to grow by gigabytes within seconds).
    assert 0 < results["flood_estop_p99_ms"] < math.inf
    assert 0 < results["flood_estop_quiet_p99_ms"] < math.inf
    assert results["flood_server_rss_growth_mib"] < 200


def test_the_camera_scenario_counts_what_a_stream_client_got() -> None:
    async def with_camera() -> dict[str, float]:
        async with bench.running_server() as server:
            return await camera(server, seconds=0.5)

    results = asyncio.run(with_camera())
    assert results["camera_stream_parts"] > 0
    assert results["camera_frames"] >= results["camera_stream_parts"]
    assert 0 < results["camera_to_client_p50_ms"] <= results["camera_to_client_p99_ms"]
    assert results["camera_recording_dropped"] == 0


def test_the_nodes_scenarios_run_on_a_fleet_of_processes() -> None:
    need("zenoh", "fleet")
    from arena.bench.nodes import nodes_estop, nodes_relay

    relayed = asyncio.run(nodes_relay(count=20))
    assert relayed["nodes_relay_same_p50_us"] > 0 and relayed["nodes_relay_cross_p50_us"] > 0
    stopped = asyncio.run(nodes_estop(nodes=2, robots=2, trials=2))
    assert stopped["nodes_estop_robots"] == 4 and stopped["nodes_estop_missing_nodes"] == 0
    assert 0 < stopped["nodes_estop_last_notice_ms"] < math.inf


def test_soak_reports_start_against_end_and_losses() -> None:
    async def short_soak() -> dict[str, float]:
        async with bench.running_server() as server:
            return await bench.soak(server, robots=3, rate=20, seconds=2.0, window=0.5)

    results = asyncio.run(short_soak())
    assert results["soak_commands_sent"] >= 3 * 20  # about 40 a robot; a busy box sends fewer
    assert results["soak_commands_unacknowledged"] == 0
    assert results["soak_commands_refused"] == 0
    assert results["soak_recording_dropped"] == 0
    # Every command is recorded (plus what the robots sent and reported).
    assert results["soak_recorded_messages"] >= results["soak_commands_sent"]
    for key in ("soak_first_p99_us", "soak_last_p99_us", "soak_rss_warm_mib", "soak_rss_end_mib"):
        assert results[key] > 0, key


def test_unknown_scenarios_are_named() -> None:
    with pytest.raises(ValueError, match="unknown scenarios: sock"):
        bench.run_benchmarks(only=["sock"])


def test_in_process_scenarios() -> None:
    assert bench.core_rate(count=200)["core_commands_per_s"] > 0
    assert bench.replay_rate(commands=200)["replay_commands_per_s"] > 0


def test_teleop_scenario_runs_on_two_simulated_buses() -> None:
    results = bench.teleop_latency(moves=5, rate=250)
    assert results["teleop_250hz_missed"] == 0
    assert results["teleop_250hz_p99_ms"] > 0


def test_usb_scenario_runs_on_the_simulated_bus() -> None:
    results = bench.usb_control_rate(seconds=0.3, rate=100, min_cycles=3)
    assert results["usb_max_control_rate_hz"] > 0
    assert results["usb_100hz_achieved_hz"] > 0


def test_the_lean_http_client_goes_on_after_the_server_closes_the_connection() -> None:
    # hypercorn ends a keep-alive connection after 1,000 requests ("Connection: close"): the
    # e-stop scenario then hung on its 501st trial.
    listener = socket.create_server(("127.0.0.1", 0))

    def serve_two_connections() -> None:
        for n in range(2):
            connection, _ = listener.accept()
            with connection:
                head = b""
                while b"\r\n\r\n" not in head:
                    head += connection.recv(1024)
                body = b'{"connection": %d}' % n
                connection.sendall(
                    b"HTTP/1.1 200 OK\r\nContent-Length: %d\r\nConnection: close\r\n\r\n"
                    % len(body)
                    + body
                )

    server = threading.Thread(target=serve_two_connections, daemon=True)
    server.start()
    http = BlockingHttp(f"http://127.0.0.1:{listener.getsockname()[1]}", timeout=5)
    request = http.request_bytes("POST", "/api/estop")
    try:
        http.send(request)
        assert http.answer() == (200, b'{"connection": 0}')
        http.send(request)
        assert http.answer() == (200, b'{"connection": 1}')
    finally:
        http.close()
        server.join(5)
        listener.close()


def test_a_relay_times_each_command_to_its_own_answer_not_one_received_before() -> None:
    # A motion tick's `execute_command` could reach the relay's slave after the answer it
    # had timed: the next command was then timed to it, the next after that sent at once,
    # and two commands in one burst left the arm where the third asked it to go (nothing
    # sent, the relay waiting for ever: seen in CI). The server here sends an
    # `execute_command` first, then closes once the timed frame came: the timing must end
    # with the close (no answer to that frame), not on the message it had before.
    listener = socket.create_server(("127.0.0.1", 0))
    stale = json.dumps({"type": "execute_command", "data": {}}, separators=(",", ":")).encode()

    def serve() -> None:
        connection, _ = listener.accept()
        with connection:
            request = b""
            while b"\r\n\r\n" not in request:
                request += connection.recv(4096)
            key = re.search(rb"Sec-WebSocket-Key: (\S+)", request, re.I)
            assert key is not None
            connection.sendall(
                b"HTTP/1.1 101 Switching Protocols\r\nUpgrade: websocket\r\n"
                b"Connection: Upgrade\r\nSec-WebSocket-Accept: "
                + accept_key(key.group(1).decode()).encode()
                + b"\r\n\r\n"
            )
            connection.sendall(encode_frame(OP_TEXT, stale))
            connection.recv(4096)  # the timed frame
            connection.sendall(encode_frame(OP_CLOSE, struct.pack("!H", 1000)))

    server = threading.Thread(target=serve, daemon=True)
    server.start()
    both = BlockingWebSocket(f"ws://127.0.0.1:{listener.getsockname()[1]}/ws/slave/x", timeout=30)
    try:
        if not both._buffer:  # (it may have come with the handshake's answer)
            select.select([both.sock], [], [])  # the early message is in
        with pytest.raises(ConnectionError, match="closed by the server"):
            time_to(EXECUTE_MARK, both, both, masked_frame(command_text(1)))
    finally:
        both.sock.close()
        server.join(30)
        listener.close()


def test_a_benchmark_commands_only_once_its_slave_is_the_robots() -> None:
    # The server answers a slave's handshake before its robot has the slave: a first command
    # sent in between reaches no slave (a twin gets targets from the next command on), and a
    # relay timed to the slave's answer would wait for ever (a candidate for a hang once seen
    # in CI). Each timed scenario first waits for its slave (`attached_slave`,
    # `wait_for_slaves`): no slave, no return; the slave the robot's, it returns.
    async def scenario() -> None:
        async with (
            bench.running_server() as server,
            httpx.AsyncClient(base_url=server.url, timeout=60) as http,
        ):
            await create_bench_robot(http, "attach")
            await create_bench_robot(http, "other")
            with pytest.raises(RuntimeError, match=r"'attach' has no slave after 0\.2 s"):
                await asyncio.to_thread(wait_for_slaves, server.url, ["attach"], 0.2)
            slave = await asyncio.to_thread(attached_slave, server.ws, "attach")
            try:
                robot = (await http.get("/api/robots/attach")).json()
                assert len(robot["slaves"]) == 1
                # one robot of two with a slave: still waiting, for the other
                with pytest.raises(RuntimeError, match="'other' has no slave"):
                    await asyncio.to_thread(wait_for_slaves, server.url, ["attach", "other"], 0.2)
            finally:
                slave.close()

    asyncio.run(scenario())


def test_no_relay_command_asks_for_a_goal_an_earlier_one_did() -> None:
    goals = [json.loads(command_text(i))["data"]["joints"][0]["value"] for i in range(1, 5101)]
    assert len(set(goals)) == len(goals)


def commands_answered(server: bench.Server) -> float:
    """The commands the server has answered so far (its `/metrics`), read without waiting on
    the event loop: a stand-in for its CPU time that grows by exactly one a command."""
    text = httpx.get(server.url + "/metrics", timeout=10).text
    return float(
        sum(
            float(line.rsplit(" ", 1)[1])
            for line in text.splitlines()
            if line.startswith("arena_commands_total{")
        )
    )


def test_the_ordinary_client_relay_runs_against_any_server_of_the_contract(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # Against Arena itself here (the floor needs packages of its own: `arena bench versus`).
    # The server's CPU is read at the start, between the phases and at the end; with a
    # counter of commands answered in its place, each phase must cost exactly one a command:
    # a reading at the wrong moment, or a phase divided by the wrong count, shows.
    async def against_arena() -> dict[str, float]:
        async with bench.running_server() as server:
            monkeypatch.setattr(server, "cpu_seconds", lambda: commands_answered(server))
            return await bench.ordinary_relay(server, "ordinary", one_at_a_time=100, burst=3000)

    results = asyncio.run(against_arena())
    assert results["p50_us"] > 0 and results["throughput_per_s"] > 0
    for key in (
        "cpu_us_per_command",
        "cpu_one_at_a_time_us_per_command",
        "cpu_burst_us_per_command",
    ):
        assert results[key] == pytest.approx(1e6, rel=1e-12), key  # one "second" a command
    monkeypatch.delenv("ARENA_FLOOR_PYTHON", raising=False)
    with pytest.raises(RuntimeError, match="ARENA_FLOOR_PYTHON"):
        asyncio.run(bench.versus_floor(rounds=1))


def test_a_servers_cpu_time_is_read_to_well_under_a_clock_tick() -> None:
    # A child spins until it has used 0.2 s of CPU, says how much exactly, and waits.
    spin = (
        "import sys, time\n"
        "while time.process_time() < 0.2: pass\n"
        "print(time.process_time(), flush=True)\n"
        "sys.stdin.read()\n"
    )
    child = subprocess.Popen(
        [sys.executable, "-c", spin], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
    )
    try:
        assert child.stdout is not None
        used = float(child.stdout.readline())
        measured = process_cpu_seconds(child.pid)
        # Not a whole number of 10 ms ticks, and within a few ms of what the child counted
        # (it prints, then blocks: a little more CPU, never less).
        assert used <= measured < used + 0.005
    finally:
        child.communicate("")
    assert process_cpu_seconds(child.pid) == 0.0  # gone (and reaped): nothing to count


def test_the_trio_floor_relays_as_the_floor_does() -> None:
    # The trio floor stands in for shared/bench/floor_relay.py in `arena bench versus`: the
    # same contract subset (create, a master's command to the slave as execute_command).
    from pathlib import Path

    from arena.bench import versus

    script = Path(versus.__file__).with_name("trio_floor.py")

    async def one_round() -> dict[str, float]:
        async with versus.running_floor(sys.executable, script) as floor:
            # Bounded: a floor that forwarded nothing would leave the relay waiting for ever.
            relay = versus.ordinary_relay(floor, "trio-floor", one_at_a_time=20, burst=200)
            return await asyncio.wait_for(relay, 60)

    results = asyncio.run(one_round())
    assert results["p50_us"] > 0
    assert results["throughput_per_s"] > 0


def test_the_contract_floor_acknowledges_every_command() -> None:
    # `--acks` makes the trio floor the contract floor of `arena bench versus`: every command
    # answered to its master as Arena answers it, and still relayed to the slave.
    from arena.bench import versus
    from arena.bench.fleet import fleet

    async def run() -> dict[str, float]:
        async with versus.running_floor(sys.executable, versus.CONTRACT_FLOOR, "--acks") as floor:
            return await asyncio.wait_for(fleet(floor, robots=3, rate=50.0, seconds=1.0), 60)

    results = asyncio.run(run())
    assert results["fleet_commands_sent"] > 50
    assert results["fleet_commands_unacknowledged"] == 0
    assert results["fleet_commands_refused"] == 0
    assert results["fleet_messages"] >= results["fleet_commands_sent"] - 3  # the slaves' too


def test_observation_to_command_counts_frame_age_round_trip_and_the_wait_for_a_step() -> None:
    def message(kind: str, **data: object) -> RecordedMessage:
        return RecordedMessage(f"/robots/arm/{kind}", "arm", kind, 0, data)

    me, other = "policy:act:0123456789ab", "policy:act:ffffffffffff"
    messages = [
        message("command", t=0.95, source=me, accepted=True),  # before the chunk came back
        message("policy", t=1.0, policy=me, latency=0.1, frame_age=0.02),
        message("command", t=1.01, source=other, accepted=True),  # another master's
        message("command", t=1.02, source=me, accepted=False),  # refused: decided nothing
        message("command", t=1.03, source=me, accepted=True),  # the first after it
        message("command", t=1.06, source=me, accepted=True),
        message("policy", t=2.0, policy=me, latency=0.2, frame_age=None),  # no camera
        message("command", t=2.04, source=me, accepted=True),
        message("policy", t=3.0, policy=me, latency=0.1, frame_age=0.0),  # none came after
    ]
    assert observation_to_command(messages, me) == [
        pytest.approx(1.03 - 0.9 + 0.02),
        pytest.approx(2.04 - 1.8),
    ]
    assert observation_to_command(messages, other) == []


def test_pause_latencies_take_the_last_target_change_and_the_first_command_after() -> None:
    from arena.bench.pause import pause_latencies

    def message(kind: str, at: float, **data: object) -> RecordedMessage:
        return RecordedMessage(f"/robots/arm/{kind}", "arm", kind, round(at * 1e9), data)

    me = "policy:act:0123456789ab"
    messages = [
        message("targets", 9.9, joints={"a": 1.0}),
        message("targets", 10.01, joints={"a": 2.0}),  # still moving after the request
        message("targets", 10.03, joints={"a": 2.5}),  # the last change: it holds from here
        message("targets", 10.5, joints={"a": 2.5}),  # the same targets again: no change
        message("command", 11.1, source=me, accepted=False),  # refused: not an action
        message("command", 11.2, source="other", accepted=True),  # another master's
        message("command", 11.3, source=me, accepted=True),  # the first action after resume
        message("targets", 11.3, joints={"a": 3.0}),
        message("targets", 20.5, joints={"a": 3.0}),  # a pause with no change after it
        message("command", 21.25, source=me, accepted=True),
    ]
    holds, firsts = pause_latencies(messages, me, [10.0, 20.0], [11.0, 21.0])
    assert holds == pytest.approx([0.03, 0.0])
    assert firsts == pytest.approx([0.3, 0.25])


def test_resume_parts_split_off_the_inference() -> None:
    from arena.bench.pause import resume_parts

    def message(kind: str, at: float, **data: object) -> RecordedMessage:
        return RecordedMessage(f"/robots/arm/{kind}", "arm", kind, round(at * 1e9), data)

    me = "policy:act:0123456789ab"
    messages = [
        message("policy", 10.2, policy=me, latency=0.3),  # observed before the resume: stale
        message("policy", 10.6, policy=me, latency=0.3),  # the fresh one: sent at 10.3
        message("command", 10.62, source=me, accepted=True),
        message("command", 10.65, source=me, accepted=True),
    ]
    observed, commanded = resume_parts(messages, me, [10.0])
    assert observed == pytest.approx([0.3]) and commanded == pytest.approx([0.02])
