"""Operators across a slow link (specs/remote-link.md): stale commands dropped, operator loss,
the link's figures. The estimator on trio's mock clock; the server across the test relay
(arena/bench/slow_link.py), on the mock clock too, so the link's delays are virtual and exact."""

from __future__ import annotations

import contextlib
import itertools
import json
import random
import time
from collections.abc import Awaitable, Callable
from types import SimpleNamespace
from typing import Any

import pytest
import trio
from trio.testing import MockClock
from trio_websocket import ConnectionClosed, WebSocketConnection, open_websocket_url

from arena.bench.slow_link import SlowLink
from arena.server import sensors_api
from arena.server.link_quality import RESYNC_AFTER, LinkQuality
from tests.conftest import RecordingSlave, RunningServer, eventually

StartServer = Callable[..., Awaitable[RunningServer]]
PERIOD = 1 / 30  # a 30 Hz master


class Master:
    """A simulated master's clock and link for the estimator: sends at trio times, its stamps
    off by `offset` seconds, each arriving `delay ± jitter` later in order (TCP)."""

    def __init__(self, quality: LinkQuality, offset: float, delay: float, jitter: float) -> None:
        self.quality = quality
        self.offset = offset
        self.delay, self.jitter = delay, jitter
        self.rng = random.Random(3)
        self.epoch = quality.wall_now() - trio.current_time()
        self.last_arrival = 0.0
        self.next_ping = 0.0

    def stamp(self, sent: float) -> float:
        return (self.epoch + sent + self.offset) * 1000

    def arrival(self, sent: float) -> float:
        lag = self.delay + self.rng.uniform(-self.jitter, self.jitter)
        self.last_arrival = max(self.last_arrival, sent + lag)
        return self.last_arrival

    async def play(self, sends: list[tuple[float, float]]) -> list[tuple[float, bool, float]]:
        """(sent, arrival) pairs in order: each admitted or not at its arrival, with pings
        (round trip 2 x delay) once a second. Returns (true age, admitted, estimated age)."""
        events: list[tuple[float, int, float]] = []  # (when, 0 ping / 1 pong / 2 command, sent)
        while sends and self.next_ping <= sends[-1][1]:
            events += [(self.next_ping, 0, 0.0), (self.next_ping + 2 * self.delay, 1, 0.0)]
            self.next_ping += 1.0
        events += [(arrived, 2, sent) for sent, arrived in sends]
        events.sort(key=lambda event: event[:2])
        seen, pings = [], []
        for when, kind, sent in events:
            await trio.sleep_until(max(when, trio.current_time()))
            if kind == 0:
                pings.append(self.quality.ping_payload())
            elif kind == 1:
                self.quality.pong(pings.pop(0))
            else:
                admitted = self.quality.admit(self.stamp(sent))
                assert self.quality.last_age is not None
                seen.append((when - sent, admitted, self.quality.last_age))
        return seen

    def steady(self, start: float, seconds: float) -> list[tuple[float, float]]:
        count = round(seconds / PERIOD)
        sends = [start + n * PERIOD for n in range(count)]
        return [(sent, self.arrival(sent)) for sent in sends]


async def test_ages_are_right_whatever_the_clock_offset_and_jitter(
    autojump_clock: MockClock,
) -> None:
    quality = LinkQuality("remote", max_age=0.4, ping_interval=1.0)
    master = Master(quality, offset=37.5, delay=0.1, jitter=0.025)  # 37.5 s ahead
    seen = await master.play(master.steady(trio.current_time(), 10.0))
    assert all(admitted for _, admitted, _ in seen)
    assert quality.stale == 0
    # Once a ping has timed the round trip, each estimate is within the jitter of the truth.
    after_first_second = seen[35:]
    assert all(abs(estimate - truth) <= 0.05 + 1e-9 for truth, _, estimate in after_first_second)
    assert quality.rtt == pytest.approx(0.2)
    assert 0.005 < quality.jitter < 0.05
    assert quality.quality() == "good"


async def test_a_stall_then_its_backlog_in_one_burst_runs_only_what_is_still_fresh(
    autojump_clock: MockClock,
) -> None:
    quality = LinkQuality("remote", max_age=0.4, ping_interval=1.0)
    master = Master(quality, offset=-2.25, delay=0.1, jitter=0.025)
    start = trio.current_time()
    await master.play(master.steady(start, 2.0))
    # 2 s stall: 60 commands held, then all delivered in one burst at the release.
    stall_start = start + 2.0
    released = stall_start + 2.0
    held = [stall_start + n * PERIOD for n in range(60)]
    seen = await master.play([(sent, released) for sent in held])
    admitted = [truth for truth, ok, _ in seen if ok]
    dropped = [truth for truth, ok, _ in seen if not ok]
    assert all(age <= 0.4 + 0.05 for age in admitted)  # the estimate's error at most
    assert all(age > 0.4 - 0.05 for age in dropped)
    assert len(dropped) == quality.stale >= 60 - round(0.45 / PERIOD) - 1
    assert len(admitted) <= round(0.45 / PERIOD) + 1  # < half a second of motion, not 2 s
    assert quality.quality() == "poor"  # dropped just now
    # The link is back: the next commands run.
    master.last_arrival = released
    after = await master.play(master.steady(released, 1.0))
    assert all(ok for _, ok, _ in after)


async def test_a_master_whose_clock_is_set_back_is_believed_again_once_the_link_is_quick(
    autojump_clock: MockClock,
) -> None:
    quality = LinkQuality("remote", max_age=0.4, ping_interval=1.0)
    master = Master(quality, offset=0.0, delay=0.05, jitter=0.0)
    await master.play(master.steady(trio.current_time(), 2.0))
    master.offset = -1.0  # NTP steps the master's clock back a second
    seen = await master.play(master.steady(trio.current_time(), 4.0))
    refused = [n for n, (_, ok, _) in enumerate(seen) if not ok]
    # For a second its stamps are no later than its last before the step (taken as
    # unstamped); then they look a second old, and are dropped only until a quick round trip
    # after RESYNC_AFTER: then believed again, for good.
    assert refused, "commands stamped a second back look a second old"
    assert refused == list(range(refused[0], refused[0] + len(refused)))
    assert len(refused) * PERIOD <= RESYNC_AFTER + 1.0 + 2 * PERIOD


async def test_unstamped_or_repeated_stamps_and_max_age_zero_never_drop(
    autojump_clock: MockClock,
) -> None:
    quality = LinkQuality("remote", max_age=0.4, ping_interval=1.0)
    assert quality.admit(None)
    assert quality.admit(1704110400000)  # the seed's example stamp, in every command
    await trio.sleep(5.0)
    assert quality.admit(1704110400000)  # no later than the last: not a clock reading
    assert quality.admit(float("nan"))
    assert quality.stale == 0
    off = LinkQuality("remote", max_age=0, ping_interval=1.0)
    master = Master(off, offset=0.0, delay=0.01, jitter=0.0)
    seen = await master.play([(0.0, 0.01), (0.1, 5.0)])  # 4.9 s late: still run
    assert [ok for _, ok, _ in seen] == [True, True]


# --- across the relay, on a real server -------------------------------------------------------


async def stamped_command(ws: WebSocketConnection, epoch: float, value: float) -> None:
    """A command stamped with this client's clock (ms since the epoch)."""
    stamp = (epoch + trio.current_time()) * 1000
    joints = [{"name": "Rotation", "value": value}]
    await ws.send_message(
        json.dumps({"type": "command", "data": {"timestamp": stamp, "joints": joints}})
    )


async def collect_acks(ws: WebSocketConnection, acks: list[dict[str, Any]]) -> None:
    with contextlib.suppress(ConnectionClosed):
        while True:
            message = json.loads(await ws.get_message())
            if message["type"] == "ack":
                acks.append(message["data"])


async def stall_scenario(
    start_server: StartServer, nursery: trio.Nursery, max_age: float
) -> tuple[list[dict[str, Any]], RecordingSlave, RunningServer]:
    """30 Hz commands through a link of 100 +- 25 ms each way: 1 s, a 2 s stall with 60
    commands held, then 1 s more. The acks, in order, and what the slave was told."""
    server = await start_server(record=False, command_max_age=max_age)
    robot = await server.app.manager.create_robot("so-arm100", robot_id="far")
    slave = RecordingSlave()
    await robot.attach_slave(slave, "arm")
    port = int(server.url.rsplit(":", 1)[1])
    link = SlowLink("127.0.0.1", port, random_seed=5)
    await nursery.start(link.serve)
    link.shape(delay=0.1, jitter=0.025)
    epoch = time.time() - trio.current_time() + 11.0  # this client's clock is 11 s ahead
    acks: list[dict[str, Any]] = []
    url = f"ws://127.0.0.1:{link.port}/ws/master/far?joint_states=false"
    async with open_websocket_url(url) as ws, trio.open_nursery() as inner:
        inner.start_soon(collect_acks, ws, acks)
        value = 0.0
        for phase in ("before", "stall", "after"):
            if phase == "stall":
                link.stall()
            if phase == "after":
                link.release()
            for _ in range(60 if phase == "stall" else 30):
                value += 0.5
                await stamped_command(ws, epoch, value)
                await trio.sleep(PERIOD)
        await eventually(lambda: len(acks) == 120, what="every command answered")
        inner.cancel_scope.cancel()
    return acks, slave, server


async def test_a_2_s_stall_does_not_replay_its_60_commands_across_the_relay(
    autojump_clock: MockClock, start_server: StartServer, nursery: trio.Nursery
) -> None:
    acks, _, server = await stall_scenario(start_server, nursery, max_age=0.4)
    status = [ack["status"] for ack in acks]
    stale = [n for n, s in enumerate(status) if s != "accepted"]
    assert all(acks[n]["code"] == "STALE_COMMAND" for n in stale)
    # The backlog: the 60 commands of the stall and the few still on their way when it
    # began (100 ms of them). Its oldest are dropped, in one run; only its newest, sent less
    # than max_age (+ the estimate's margin) before the release, run: at most half a second
    # of motion, not two. The link's delay and jitter alone drop nothing.
    assert stale == list(range(stale[0], stale[-1] + 1))
    assert 30 - round(0.1 / PERIOD) - 1 <= stale[0] <= 30
    assert 90 - (stale[-1] + 1) <= round(0.5 / PERIOD)
    assert status[90:] == ["accepted"] * 30
    assert server.app.metrics.stale_commands["far"] == len(stale)


async def test_without_max_age_the_backlog_s_oldest_commands_run_late_in_a_burst(
    autojump_clock: MockClock, start_server: StartServer, nursery: trio.Nursery
) -> None:
    # Today's behaviour, kept for command_max_age = 0: the backlog arrives at once and its
    # OLDEST commands run, 2 s late, in a burst (until the rate limit refuses the rest, the
    # newest among them: the opposite of what the operator wants).
    acks, _, _ = await stall_scenario(start_server, nursery, max_age=0)
    status = [ack["status"] for ack in acks]
    assert "STALE_COMMAND" not in [ack.get("code") for ack in acks]
    # the first second, and the backlog's oldest (stalled from 27 on), 1.8 s late or more
    assert status[:35] == ["accepted"] * 35
    refused = [n for n, s in enumerate(status) if s != "accepted"]
    assert refused and all(acks[n]["code"] == "RATE_LIMITED" for n in refused)


async def heartbeats(ws: WebSocketConnection, every: float) -> None:
    with contextlib.suppress(ConnectionClosed):
        while True:
            await ws.send_message('{"type": "heartbeat"}')
            await trio.sleep(every)


async def test_operator_loss_stops_the_arm_and_the_recovered_link_moves_only_anew(
    autojump_clock: MockClock, start_server: StartServer, nursery: trio.Nursery
) -> None:
    # Across 100 ms each way, the link stalls for 3 s: the robot hears nothing, and stops
    # (its loss policy, an e-stop) within the heartbeat bound of the last message it heard.
    # What the operator sent meanwhile (a move to 30 degrees) arrives after the release and
    # never moves the arm; after a reset the arm holds until a new command comes.
    timeout = 1.0
    server = await start_server(record=False, heartbeat_timeout=timeout, heartbeat_interval=0.3)
    robot = await server.app.manager.create_robot("so-arm100", robot_id="far")
    slave = RecordingSlave()
    await robot.attach_slave(slave, "arm")
    port = int(server.url.rsplit(":", 1)[1])
    link = SlowLink("127.0.0.1", port, random_seed=9)
    await nursery.start(link.serve)
    link.shape(delay=0.1)
    epoch = time.time() - trio.current_time()
    url = f"ws://127.0.0.1:{link.port}/ws/master/far?joint_states=false"
    async with open_websocket_url(url) as ws, trio.open_nursery() as inner:
        acks: list[dict[str, Any]] = []
        inner.start_soon(collect_acks, ws, acks)
        inner.start_soon(heartbeats, ws, 0.3)
        await stamped_command(ws, epoch, 10.0)
        await eventually(lambda: slave.targets and slave.targets[-1][1]["Rotation"] == 10.0)
        link.stall()
        last_heard = trio.current_time()  # nothing sent from now on reaches the server
        stopped: list[float] = []

        async def note_the_stop() -> None:  # on the mock clock: exact to its 10 ms polls
            await eventually(lambda: robot.snapshot().mode == "estopped", what="the e-stop")
            stopped.append(trio.current_time())

        inner.start_soon(note_the_stop)
        with contextlib.suppress(ConnectionClosed):  # (closed once the release shows it)
            for _ in range(60):  # the operator goes on: 2 s of commands toward 30 degrees
                await stamped_command(ws, epoch, 30.0)
                await trio.sleep(PERIOD)
        await eventually(lambda: bool(stopped), what="the e-stop")
        assert timeout - 0.1 <= stopped[0] - last_heard <= timeout + 0.02  # (a poll's slack)
        await trio.sleep_until(last_heard + 3.0)
        link.release()
        await trio.sleep(1.0)  # the backlog arrives at the server, on a link that is gone
        inner.cancel_scope.cancel()
    assert all(target["Rotation"] <= 10.0 for _, target in slave.targets)
    await robot.reset()
    targets_at_reset = len(slave.targets)
    async with open_websocket_url(url) as ws, trio.open_nursery() as inner:
        acks = []
        inner.start_soon(collect_acks, ws, acks)
        inner.start_soon(heartbeats, ws, 0.3)
        await trio.sleep(2.0)  # connected, no command yet: the arm holds
        assert all(t["Rotation"] == 10.0 for _, t in slave.targets[targets_at_reset:])
        await stamped_command(ws, epoch, -5.0)
        await eventually(lambda: slave.targets[-1][1]["Rotation"] == -5.0, what="the new move")
        await eventually(lambda: bool(acks), what="its ack")
        inner.cancel_scope.cancel()
    assert acks[-1]["status"] == "accepted"
    assert all(target["Rotation"] <= 10.0 for _, target in slave.targets)


async def test_the_link_shows_in_the_robot_s_details_and_on_metrics(
    autojump_clock: MockClock, start_server: StartServer, nursery: trio.Nursery
) -> None:
    server = await start_server(record=False)
    robot = await server.app.manager.create_robot("so-arm100", robot_id="far")
    await robot.attach_slave(RecordingSlave(), "arm")
    port = int(server.url.rsplit(":", 1)[1])
    link = SlowLink("127.0.0.1", port, random_seed=2)
    await nursery.start(link.serve)
    link.shape(delay=0.1, jitter=0.025)  # 200 ms round trip, +-50
    epoch = time.time() - trio.current_time()
    url = f"ws://127.0.0.1:{link.port}/ws/master/far?id=overseas&joint_states=false"
    async with (
        open_websocket_url(url) as ws,
        trio.open_nursery() as inner,
        server.client() as http,
    ):
        inner.start_soon(collect_acks, ws, [])
        for n in range(90):  # 3 s at 30 Hz
            await stamped_command(ws, epoch, n / 10)
            await trio.sleep(PERIOD)
        master = (await http.get("/api/robots/far")).json()["master"]
        assert master["id"] == "overseas"
        shown = master["link"]
        assert 0.15 <= shown["rtt"] <= 0.25
        assert 0.0 < shown["jitter"] < 0.05
        assert shown["dropped_stale"] == 0 and 85 <= shown["stamped"] <= 90  # (some on the way)
        assert shown["quality"] in ("good", "fair")
        text = (await http.get("/metrics")).text
        assert f'arena_master_rtt_seconds{{robot="far"}} {shown["rtt"]}' in text
        assert 'arena_stale_commands_total{robot="far"} 0' in text
        # A 2 s stall: its backlog is dropped, counted, and the link shows poor.
        link.stall()
        for n in range(60):
            await stamped_command(ws, epoch, 9 + n / 10)
            await trio.sleep(PERIOD)
        link.release()
        await eventually(
            lambda: server.app.master_links["far"]["overseas"].stale > 0,
            what="the backlog's drops",
        )
        await trio.sleep(0.5)
        status = (await http.get("/api/robots/far/status")).json()
        dropped = status["master"]["link"]["dropped_stale"]
        assert dropped >= 40 and status["master"]["link"]["quality"] == "poor"
        text = (await http.get("/metrics")).text
        assert f'arena_stale_commands_total{{robot="far"}} {dropped}' in text
        assert 'arena_master_link_quality{robot="far"} 3' in text
        inner.cancel_scope.cancel()
    await eventually(lambda: "far" not in server.app.master_links, what="the link forgotten")


# --- video keeps up ---------------------------------------------------------------------------


class PatternCamera:
    """A camera of 9 kB frames at 30 fps on trio's clock."""

    def __init__(self) -> None:
        self.latest: SimpleNamespace | None = None
        self.changed = trio.Event()
        self.streams_dropped = 0

    async def run(self) -> None:
        for seq in itertools.count():
            self.latest = SimpleNamespace(seq=seq, wall_time=trio.current_time(), jpeg=b"j" * 9000)
            self.changed.set()
            self.changed = trio.Event()
            await trio.sleep(1 / 30)

    async def next_frame(self, after: int) -> SimpleNamespace:
        while self.latest is None or self.latest.seq <= after:
            await self.changed.wait()
        return self.latest


class SlowClientSocket:
    """A socket whose kernel takes every write at once and hands it to a client that takes
    `rate` bytes a second: notes when each part's last byte reached the client."""

    def __init__(self, rate: float) -> None:
        self.rate = rate
        self.free_at = 0.0  # when the client will have everything written so far
        self.delivered: list[tuple[float, float]] = []  # (delivered, the frame's time)

    async def send_all(self, data: bytes) -> None:
        self.free_at = max(self.free_at, trio.current_time()) + len(data) / self.rate
        if b"X-Timestamp: " in data:
            stamp = float(data.split(b"X-Timestamp: ")[1].split(b"\r\n")[0])
            self.delivered.append((self.free_at, stamp))

    def queued(self) -> int:
        return max(0, round((self.free_at - trio.current_time()) * self.rate))


@pytest.mark.parametrize("waits", [True, False])
async def test_a_slow_client_gets_the_newest_frames_at_its_rate_never_a_backlog(
    autojump_clock: MockClock, waits: bool
) -> None:
    # 30 fps of 9 kB frames to a client that takes 90 kB/s (10 frames a second). Waiting for
    # the kernel to hand each part over, the stream sends about 10 a second, each as old when
    # it arrives as its time on the link and a camera period, however long it runs. Without waiting
    # (False: the stream as it was) the kernel's queue grows and with it every frame's age.
    camera, client = PatternCamera(), SlowClientSocket(90_000)
    async with trio.open_nursery() as nursery:
        nursery.start_soon(camera.run)
        await trio.sleep(0.1)
        with trio.move_on_after(20.0):
            await sensors_api.send_frames(camera, client, client.queued if waits else None)  # type: ignore[arg-type]
        nursery.cancel_scope.cancel()
    arrived = [(at, stamp) for at, stamp in client.delivered if at <= trio.current_time()]
    ages = [at - stamp for at, stamp in arrived]
    if waits:
        assert 9 * 20 <= len(arrived) <= 10 * 20 + 1
        # at most the rest of the last part ahead of it, itself, a camera period and a poll
        on_the_link = (sensors_api.STREAM_QUEUE_BYTES + 9100) / 90_000
        assert max(ages) <= on_the_link + 1 / 30 + sensors_api.STREAM_DRAIN_POLL + 1e-6
    else:
        assert max(ages) > 10.0  # half the run behind, and growing


async def test_the_link_s_quality_goes_by_its_pongs_and_its_stale_drops(
    autojump_clock: MockClock,
) -> None:
    quality = LinkQuality("remote", max_age=0.4, ping_interval=2.0)
    await trio.sleep(30.0)
    assert quality.quality() == "unknown"  # never pinged (a fleet's tunnel): no verdict
    payload = quality.ping_payload()
    await trio.sleep(0.05)
    quality.pong(payload)
    assert quality.quality() == "good"
    payload = quality.ping_payload()
    await trio.sleep(0.2)
    quality.pong(payload)  # 200 ms: about 100 ms one way, under half of max_age
    assert quality.quality() == "good"
    payload = quality.ping_payload()
    await trio.sleep(0.5)
    quality.pong(payload)  # 500 ms round trip: 250 ms one way, above half of max_age
    assert quality.quality() == "fair"
    quality.ping_payload()
    await trio.sleep(3 * 2.0 + 0.6)  # three pings' time without an answer
    assert quality.quality() == "poor"
    assert quality.as_dict()["rtt"] == pytest.approx(0.5)


async def test_a_group_master_s_stale_command_is_refused_and_moves_no_member(
    autojump_clock: MockClock, start_server: StartServer
) -> None:
    server = await start_server(record=False, command_max_age=0.4)
    for robot_id in ("left", "right"):
        robot = await server.app.manager.create_robot("so-arm100", robot_id=robot_id)
        await robot.attach_slave(RecordingSlave(), "arm")
    async with server.client() as http:
        made = await http.post("/api/groups", json={"id": "line", "members": ["left", "right"]})
        assert made.status_code == 201, made.text

    def goals() -> list[float]:
        manager = server.app.manager
        return [manager.get(r).snapshot().joint("Rotation").goal for r in ("left", "right")]

    epoch = time.time() - trio.current_time() - 30.0  # this client's clock is 30 s behind
    url = f"{server.url.replace('http', 'ws')}/ws/master/line?joint_states=false"
    async with open_websocket_url(url) as ws:

        async def answer() -> dict[str, Any]:
            while True:
                message = json.loads(await ws.get_message())
                if message["type"] in ("ack", "error"):
                    return message

        stamp = (epoch + trio.current_time()) * 1000
        await stamped_command(ws, epoch, 5.0)
        assert (await answer())["data"]["status"] == "accepted"
        assert goals() == [5.0, 5.0]
        await trio.sleep(2.0)  # this command is held 2 s on its way: sent then, run now?
        joints = [{"name": "Rotation", "value": 20.0}]
        late = {"type": "command", "data": {"timestamp": stamp + 1, "joints": joints}}
        await ws.send_message(json.dumps(late))
        refused = await answer()
        assert (refused["type"], refused["data"]["code"]) == ("error", "STALE_COMMAND")
        assert goals() == [5.0, 5.0]
        await stamped_command(ws, epoch, 6.0)  # a fresh one runs
        assert (await answer())["data"]["status"] == "accepted"
        assert goals() == [6.0, 6.0]
    assert server.app.metrics.stale_commands["left"] == 1


async def test_an_intervening_master_and_the_one_it_paused_each_show_their_own_link(
    autojump_clock: MockClock, start_server: StartServer
) -> None:
    server = await start_server(record=False)
    robot = await server.app.manager.create_robot("so-arm100", robot_id="arm")
    await robot.attach_slave(RecordingSlave(), "s")
    base = f"{server.url.replace('http', 'ws')}/ws/master/arm?joint_states=false"
    epoch = time.time() - trio.current_time()

    async def details() -> dict[str, Any]:
        async with server.client() as http:
            return dict((await http.get("/api/robots/arm")).json())

    # Each socket is read while open (its pings answered then, never while it closes).
    async with open_websocket_url(f"{base}&id=first") as first, trio.open_nursery() as outer:
        outer.start_soon(collect_acks, first, [])
        await stamped_command(first, epoch, 1.0)
        url = f"{base}&id=second&intervene=1"
        async with open_websocket_url(url) as second, trio.open_nursery() as inner:
            inner.start_soon(collect_acks, second, [])
            await stamped_command(second, epoch, 2.0)
            await trio.sleep(PERIOD)  # (a stamp no later than the last is not a clock reading)
            await stamped_command(second, epoch, 3.0)
            await eventually(
                lambda: server.app.master_links["arm"]["second"].stamped == 2,
                what="the corrector's commands",
            )
            shown = await details()
            assert shown["master"]["id"] == "second" and shown["paused_master"]["id"] == "first"
            assert shown["master"]["link"]["stamped"] == 2
            assert shown["paused_master"]["link"]["stamped"] == 1
            await second.send_message(json.dumps({"type": "release"}))  # hands back
            await eventually(lambda: robot.snapshot().master.peer_id == "first", what="back")
            inner.cancel_scope.cancel()
        await eventually(
            lambda: set(server.app.master_links["arm"]) == {"first"}, what="the corrector gone"
        )
        assert (await details())["master"]["link"]["stamped"] == 1
        outer.cancel_scope.cancel()
    await eventually(lambda: "arm" not in server.app.master_links, what="both links forgotten")
