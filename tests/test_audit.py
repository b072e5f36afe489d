"""The audit trail (specs/api.md, "Audit"), read back from the recording: every state-changing
REST route of the app (walked from its own URL map, so that a route added without its audit
fails here) and every state-changing WebSocket message is recorded once on each robot it acts
on, with who did it; a refused request or connection changed nothing and is not recorded.

Each change is made by a user of its own (a token's `sub`), so the records of each are told
apart. The server is a fleet of one node, so that the fleet's e-stop is walked too."""

from __future__ import annotations

import json
import shutil
from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import trio
from trio_websocket import open_websocket_url

from arena.protocol.messages import MAX_MESSAGE_BYTES
from arena.recording.mcap_file import read_recording
from arena.robot.episodes import Episode
from arena.robot.handle import Robot
from arena.robot.links import MasterLink
from arena.server.access import route_of
from arena.server.origin import SAFE_METHODS
from arena.servo.sim_pty import PtySimBus
from tests.conftest import REPOSITORY, RunningServer, eventually, need
from tests.hardware import running_sim, servo_torque
from tests.test_server_ws import closed_with, receive
from tests.test_users import SECRET, StartServer, bearer, token

#: One audit record: (robot, action, detail).
Record = tuple[str, str, str]


@pytest.fixture
def sim(tmp_path: Path) -> Iterator[PtySimBus]:
    yield from running_sim(tmp_path)


def state_changing_routes(server: RunningServer) -> set[str]:
    """Every route of the app that may change something, as the audit names it."""
    return {
        " ".join(route_of(method, rule.rule))
        for rule in server.app.url_map.iter_rules()
        for method in rule.methods or ()
        if method not in SAFE_METHODS
    }


class Walk:
    """Calls made as users of their own, and the records each must leave."""

    def __init__(self, server: RunningServer, http: Any) -> None:
        self.server = server
        self.http = http
        self.expected: dict[str, Counter[Record]] = {}
        self.walked: set[str] = set()

    def user(self) -> str:
        name = f"user-{len(self.expected)}"
        self.expected[name] = Counter()
        return name

    def route(self, method: str, path: str) -> str:
        rule, _ = self.server.app.url_map.bind("localhost").match(
            path, method=method, return_rule=True
        )
        return " ".join(route_of(method, rule.rule))

    async def change(
        self,
        method: str,
        path: str,
        body: Any = None,
        *,
        status: int = 200,
        robots: tuple[str, ...] = (),
        detail: str | None = None,
    ) -> Any:
        """A change that succeeds, recorded on each of `robots` with its status."""
        user = self.user()
        answer = await self.http.request(
            method, path, json=body, headers=bearer(token("admin", sub=user))
        )
        assert answer.status_code == status, (method, path, answer.text)
        route = self.route(method, path)
        self.walked.add(route)
        for robot in robots:
            self.expected[user][(robot, route, detail or str(status))] += 1
        return answer.json()

    async def refused(self, method: str, path: str, content: bytes, status: int) -> None:
        """A refused request: nothing recorded."""
        user = self.user()
        headers = {**bearer(token("admin", sub=user)), "Content-Type": "application/json"}
        answer = await self.http.request(method, path, content=content, headers=headers)
        assert answer.status_code == status, (method, path, answer.text)


class Highlighter:
    """The lightest master with a highlight (a policy with the `highlight` strategy has one:
    tests/test_strategies_server.py), so that the walk reaches `POST .../highlight`."""

    kind = "highlighter"
    autonomous = False
    takes_over = False

    def __init__(self, robot: Robot) -> None:
        self.robot = robot

    async def run(self, link: MasterLink) -> None:
        await trio.sleep_forever()

    async def highlight(self) -> Episode:
        return await self.robot.highlight("t", 1.0, 0.0)


async def test_every_change_is_audited_once_with_who_and_no_refusal_is(
    start_server: StartServer, sim: PtySimBus, tmp_path: Path
) -> None:
    need("zenoh", "fleet")
    (tmp_path / "jwt-secret").write_bytes(SECRET)
    recordings = tmp_path / "recordings"
    recordings.mkdir()
    shutil.copy(REPOSITORY / "recordings" / "golden" / "gentle-wave.mcap", recordings)
    (tmp_path / "arena.toml").write_text("# the robots are made below, over REST\n")
    server = await start_server(
        config_file=str(tmp_path / "arena.toml"),
        jwt_secret_file=str(tmp_path / "jwt-secret"),
        recordings_dir=str(recordings),
        calibration_dir=str(tmp_path / "calibration"),
        node="n0",
        fleet_listen=("tcp/127.0.0.1:0",),
        sim_leader="so-arm100",
    )
    arm = "/api/robots/arm"
    async with server.client() as http:
        walk = Walk(server, http)
        change = walk.change
        await change("POST", "/api/robots", {"id": "arm"}, status=201, robots=("arm",))
        await change("POST", "/api/robots", {"id": "other"}, status=201, robots=("other",))
        usb = {"type": "usb-slave", "port": str(sim.link)}
        await change("POST", f"{arm}/slaves", usb, status=201, robots=("arm",))
        await eventually(lambda: all(servo_torque(sim).values()), what="torque on")
        for step in ("start", "capture", "finish"):
            await change("POST", f"{arm}/calibration/{step}", robots=("arm",))
        await change("POST", f"{arm}/calibration/start", robots=("arm",))
        await change("POST", f"{arm}/calibration/cancel", robots=("arm",))
        mock = await change(
            "POST", f"{arm}/slaves", {"type": "mock-slave"}, status=201, robots=("arm",)
        )
        await change("DELETE", f"{arm}/slaves/{mock['id']}", robots=("arm",))
        await change("PUT", f"{arm}/workspace", {"margin": 0.01}, robots=("arm",))
        joints = {"joints": [{"name": "Rotation", "value": 5}]}
        await change("PUT", f"{arm}/joints", joints, robots=("arm",))
        reader = bearer(token("admin", sub="reader"))
        pose = (await http.get(f"{arm}/pose", headers=reader)).json()["commanded"]
        await change("PUT", f"{arm}/pose", {"position": pose["position"]}, robots=("arm",))
        await change("POST", f"{arm}/move", {"joints": {"Rotation": 6}}, robots=("arm",))
        await change("PUT", f"{arm}/teleop", {"deadman": 300}, robots=("arm",))
        guide = {"joints": ["Rotation"], "torque": 20}
        await change("POST", f"{arm}/compliance", guide, status=201, robots=("arm",))
        await change("DELETE", f"{arm}/compliance", robots=("arm",))
        await change("POST", f"{arm}/play-sequence/gentle-wave", robots=("arm",))
        await change("POST", f"{arm}/stop-sequence", robots=("arm",))
        sequence = {"type": "mock-sequence", "sequences": ["gentle-wave"], "loop": True}
        await change("POST", f"{arm}/master", sequence, status=201, robots=("arm",))
        await change("POST", f"{arm}/master/pause", robots=("arm",))
        await change("POST", f"{arm}/master/resume", robots=("arm",))
        await change("POST", f"{arm}/intervention", status=201, robots=("arm",))
        await change("DELETE", f"{arm}/intervention", robots=("arm",))
        await change("DELETE", f"{arm}/master", robots=("arm",))
        replay = {"recording": "gentle-wave.mcap", "speed": 100}
        await change("POST", f"{arm}/replay", replay, status=201, robots=("arm",))
        await change("DELETE", f"{arm}/master", robots=("arm",))
        leader = {"type": "usb-master", "port": server.app.sim_leaders.leaders[0].port}
        await change("POST", f"{arm}/master", leader, status=201, robots=("arm",))
        moved = {"joints": [{"name": "Rotation", "value": 5}]}
        await change("PUT", f"{arm}/leader/joints", moved, robots=("arm",))
        await change("DELETE", f"{arm}/master", robots=("arm",))
        camera = {"name": "front", "source": "test-pattern", "fps": 5, "width": 64, "height": 48}
        await change("POST", f"{arm}/cameras", camera, status=201, robots=("arm",))
        await change("DELETE", f"{arm}/cameras/front", robots=("arm",))
        await change("POST", f"{arm}/episodes/start", {"task": "t"}, status=201, robots=("arm",))
        await change("POST", f"{arm}/episodes/stop", robots=("arm",))
        await change("POST", f"{arm}/episodes/start", {"task": "t"}, status=201, robots=("arm",))
        await change("POST", f"{arm}/episodes/discard", robots=("arm",))
        robot = server.app.manager.get("arm")
        highlighter = await robot.attach_master(Highlighter(robot))
        await change("POST", f"{arm}/highlight", status=201, robots=("arm",))
        await robot.detach_master(highlighter)
        await change("POST", f"{arm}/estop", robots=("arm",))
        await change("POST", f"{arm}/reset", robots=("arm",))
        both = ("arm", "other")
        await change("POST", "/api/estop", robots=both)
        await change("POST", "/api/fleet/estop", robots=both, detail="from node n0")
        group = {"id": "pair", "members": ["arm", "other"]}
        await change("POST", "/api/groups", group, status=201, robots=both)
        await change("POST", "/api/groups/pair/reset", robots=both)
        await change("POST", "/api/groups/pair/estop", robots=both)
        await change("POST", "/api/groups/pair/reset", robots=both)
        # The recording switched off and on: the stop is recorded into the file it closes.
        await change("POST", "/api/recordings/current/stop", robots=both, detail="requested")
        await change("POST", "/api/recordings", status=201, robots=both)
        await change("POST", "/api/config/reload", robots=both)  # (the file declares none)

        # WebSockets: a master's e-stop, reset and release; a group master's, on each member.
        url = server.ws_url
        for path, robots in (("/ws/master/arm", ("arm",)), ("/ws/master/pair", both)):
            user = walk.user()
            group = path.endswith("pair")
            ws_url = f"{url}{path}?id=m-{user}&token={token('operator', sub=user)}"
            async with open_websocket_url(ws_url) as ws:
                await receive(ws, "state")
                for message in ("estop", "reset", "release"):
                    await ws.send_message(json.dumps({"type": message}))
                await receive(ws, "released")
            actions = ["connect group master" if group else "connect master"]
            actions += ["estop over WebSocket", "reset over WebSocket", "release over WebSocket"]
            for robot in robots:
                for action in actions:
                    walk.expected[user][(robot, action, f"m-{user}")] += 1
        user = walk.user()
        slave_url = f"{url}/ws/slave/arm?id=s-{user}&token={token('admin', sub=user)}"
        robot = server.app.manager.get("arm")
        async with open_websocket_url(slave_url):
            await eventually(
                lambda: any(s.peer_id == f"s-{user}" for s in robot.snapshot().slaves),
                what="the slave attached",
            )
        walk.expected[user][("arm", "connect slave", f"s-{user}")] += 1
        # A group master refused in part (another master holds a member) claims nothing.
        holder = await server.app.manager.get("other").connect_master("holder")
        user = walk.user()
        group_url = f"{url}/ws/master/pair?token={token('operator', sub=user)}"
        async with open_websocket_url(group_url) as ws:
            assert (await receive(ws, "error"))["data"]["code"] == "MASTER_ACTIVE"
            assert await closed_with(ws) == 4409
        await holder.release()

        # Refusals change nothing, and are not recorded: a body too large (413), one that is
        # not what the route takes (422), an e-stopped robot (423), and every route sent a body
        # it does not take.
        await walk.refused("PUT", f"{arm}/joints", b" " * (MAX_MESSAGE_BYTES + 1), 413)
        await walk.refused("PUT", f"{arm}/joints", b'{"joints": [{"name": "Rotation"}]}', 422)
        await walk.refused("POST", f"{arm}/reset", b'{"reason": "no body here"}', 400)
        await http.post(f"{arm}/estop", headers=bearer(token("viewer", sub="setup")))
        await walk.refused("POST", f"{arm}/play-sequence/gentle-wave", b"", 423)
        for route in sorted(walk.walked):
            method, template = route.split(" ")
            path = template.format(
                robot_id="arm", slave_id="none", name="front", sequence_id="gentle-wave",
                group_id="pair",
            )  # fmt: skip
            if path == "/api/recordings/front/stop":
                path = "/api/recordings/current/stop"
            user = walk.user()
            headers = {**bearer(token("admin", sub=user)), "Content-Type": "application/json"}
            answer = await http.request(method, path, content=b'{"zz": 1}', headers=headers)
            assert 400 <= answer.status_code < 500, (route, answer.text)

        # The last changes: a group and a robot deleted (recorded as asked: once done there is
        # nowhere to record them).
        await change("DELETE", "/api/groups/pair", robots=both)
        await change("DELETE", "/api/robots/other", robots=("other",), detail="requested")
    assert walk.walked == state_changing_routes(server), "a route the audit walk misses"
    server.stop.set()
    await server.done.wait()

    found: dict[str, Counter[Record]] = {user: Counter() for user in walk.expected}
    expected = walk.expected
    for path in sorted(recordings.glob("arena-*.mcap")):
        for message in read_recording(path).messages:
            if message.kind == "audit" and message.data["user"] in found:
                data = message.data
                found[data["user"]][(message.robot_id, data["action"], data["detail"])] += 1
    wrong = {
        user: {"missing": sorted(want - found[user]), "extra": sorted(found[user] - want)}
        for user, want in expected.items()
        if found[user] != want
    }
    assert not wrong, "\n".join(f"{user}: {diff}" for user, diff in wrong.items())
