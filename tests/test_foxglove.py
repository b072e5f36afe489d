"""Foxglove: forward kinematics, the view in every recording, the live server and the layout.

Every Foxglove message is decoded with the protobuf schema that the `foxglove-sdk` package
ships for its type (and that the file or the live server advertised: they must be the same).
"""

from __future__ import annotations

import base64
import hashlib
import io
import itertools
import json
import math
import random
import re
import socket
import struct
import sys
from collections.abc import AsyncIterator, Awaitable, Callable
from pathlib import Path
from typing import Any

import foxglove.messages
import numpy as np
import pytest
import trimesh
import trio
import yourdfpy
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from mcap.reader import make_reader
from trio.testing import MockClock
from trio_websocket import WebSocketConnection, open_websocket_url

from arena import cli
from arena.protocol.errors import ArenaError, ErrorCode
from arena.recording import glb
from arena.recording.foxglove import Twin
from arena.recording.mcap_file import read_recording, write_recording
from arena.robot.kinematics import Kinematics, to_matrix
from arena.robot.meshes import stl_vertices, visuals
from arena.robot.model import load_robot_model
from arena.sensors.sources import read_pattern_counter
from arena.server.config import ServerConfig
from tests.conftest import RunningServer
from tests.scenarios import record_scenario
from tests.test_cameras import jpeg_rgb
from tests.test_recording import session_scenario

MODEL = load_robot_model("so-arm100")
SPECS = {joint.name: joint for joint in MODEL.joints}
SDK_TYPES = {"foxglove.FrameTransforms", "foxglove.SceneUpdate", "foxglove.Log"}


def shipped_schema(name: str) -> bytes:
    """The FileDescriptorSet that foxglove-sdk ships for a message type."""
    return bytes(getattr(foxglove.messages, name.removeprefix("foxglove.")).get_schema().data)


_classes: dict[str, Any] = {}


def decode(name: str, payload: bytes) -> Any:
    """A message decoded with the SDK's own schema; it must re-encode to the same bytes (no
    unknown or misplaced fields)."""
    if name not in _classes:
        files = descriptor_pb2.FileDescriptorSet.FromString(shipped_schema(name))
        pool = descriptor_pool.DescriptorPool()
        for file in files.file:
            pool.Add(file)
        _classes[name] = message_factory.GetMessageClass(pool.FindMessageTypeByName(name))
    message = _classes[name].FromString(payload)
    assert message.SerializeToString() == payload
    return message


def glb_triangles(data: bytes) -> Any:
    """The corners of a GLB's triangles, read by trimesh (three rows a triangle)."""
    scene = trimesh.load(io.BytesIO(data), file_type="glb", process=False)
    (mesh,) = scene.geometry.values()
    return mesh.vertices[mesh.faces].reshape(-1, 3)


def foxglove_turn(points: Any) -> Any:
    """What Foxglove does to a glTF model: a quarter turn about X, from Y-up to Z-up
    (`rotateX(pi / 2)` in its model cache), as float32 like the STL it came from."""
    return np.column_stack((points[:, 0], -points[:, 2], points[:, 1])).astype("<f4")


def test_a_mesh_as_glb_keeps_every_triangle_and_indexes_past_65535_corners() -> None:
    rng = np.random.default_rng(7)
    corners = rng.random((3 * 30_000, 3)).astype("<f4")  # 90,000 distinct corners
    shown = foxglove_turn(glb_triangles(glb.from_triangles(corners)))
    assert np.array_equal(shown, corners)
    small = glb.from_triangles(corners[:9])
    assert len(small) % 4 == 0 and small[:4] == b"glTF"
    with pytest.raises(ValueError):
        glb.from_triangles(corners[:4])  # not whole triangles


def test_robot_types_ship_their_meshes_as_glb_made_from_the_very_stl() -> None:
    # A server converts nothing for the robot types Arena ships: each binary STL has its GLB
    # beside it, and it must be what converting that STL gives (else: regenerate with
    # `python -m arena.recording.glb arena/robot_types/*/meshes/*.stl`).
    stls = sorted(Path(MODEL.urdf_path).parents[1].glob("*/meshes/*.stl"))
    assert stls
    for stl in stls:
        source = hashlib.sha256(stl.read_bytes()).hexdigest()
        shipped = stl.with_suffix(".glb").read_bytes()
        assert glb.source_of(shipped) == source, stl.name
        assert shipped == glb.from_triangles(stl_vertices(stl), source), stl.name


def test_a_glb_made_from_other_bytes_is_not_used(tmp_path: Path) -> None:
    stl = tmp_path / "part.stl"
    stl.write_bytes(visuals(MODEL.urdf_path)[0].path.read_bytes())
    stale = glb.from_triangles(np.zeros((3, 3)), "0" * 64)  # made from another STL
    stl.with_suffix(".glb").write_bytes(stale)
    made = glb.for_stl(stl)
    assert made != stale and glb.source_of(made) == hashlib.sha256(stl.read_bytes()).hexdigest()
    assert np.array_equal(foxglove_turn(glb_triangles(made)), stl_vertices(stl).astype("<f4"))
    assert glb.source_of(b"not a glb at all") is None


def test_forward_kinematics_matches_yourdfpy() -> None:
    kinematics = Kinematics.from_urdf(MODEL.urdf_path)
    reference = yourdfpy.URDF.load(str(MODEL.urdf_path), load_meshes=False)
    rng = random.Random(7)
    for _ in range(200):
        values = {joint.name: rng.uniform(-math.pi, math.pi) for joint in kinematics.joints}
        reference.update_cfg(values)
        poses = kinematics.link_poses(values)
        assert set(poses) == set(reference.link_map)
        for link, pose in poses.items():
            expected = reference.get_transform(link, kinematics.root)
            assert np.abs(np.array(to_matrix(pose)) - expected).max() < 1e-6


def test_kinematics_of_prismatic_fixed_and_malformed_trees() -> None:
    urdf = """<robot name="r"><link name="a"/><link name="b"/><link name="c"/>
      <joint name="slide" type="prismatic"><parent link="a"/><child link="b"/>
        <origin xyz="0 0 1" rpy="0 0 1.5707963267948966"/><axis xyz="1 0 0"/></joint>
      <joint name="bolt" type="fixed"><parent link="b"/><child link="c"/>
        <origin xyz="1 0 0"/></joint></robot>"""
    poses = Kinematics.from_urdf(urdf).link_poses({"slide": 0.5})
    # the slide moves along b's x, which the origin's yaw turned to a's y
    assert np.allclose(poses["b"][1], (0.0, 0.5, 1.0))
    assert np.allclose(poses["c"][1], (0.0, 1.5, 1.0))
    cycle = '<robot name="r"><link name="a"/><link name="b"/></robot>'
    with pytest.raises(ValueError, match="one root"):
        Kinematics.from_urdf(cycle)


def sdk_tree(twin: Twin, tree: str, degrees: dict[str, float], ns: int) -> bytes:
    """A tree as foxglove-sdk's own `FrameTransforms` encodes it."""
    fm = foxglove.messages
    stamp = fm.Timestamp(ns // 1_000_000_000, ns % 1_000_000_000)

    def transform(parent: str, child: str, pose: Any) -> Any:
        (qx, qy, qz, qw), (x, y, z) = pose
        return fm.FrameTransform(
            timestamp=stamp,
            parent_frame_id=parent,
            child_frame_id=child,
            translation=fm.Vector3(x=x, y=y, z=z),
            rotation=fm.Quaternion(x=qx, y=qy, z=qz, w=qw),
        )

    kinematics = twin.kinematics
    root = twin.frame(tree, kinematics.root)
    found = [transform("world", root, ((0.0, 0.0, 0.0, 1.0), (0.0, 0.0, 0.0)))]
    values = {SPECS[name].urdf_name: SPECS[name].to_urdf(v) for name, v in degrees.items()}
    for joint, pose in kinematics.joint_transforms(values):
        found.append(transform(twin.frame(tree, joint.parent), twin.frame(tree, joint.child), pose))
    return bytes(fm.FrameTransforms(transforms=found).encode())


def test_transforms_are_encoded_byte_for_byte_as_the_sdk_encodes_them() -> None:
    """Arena writes `FrameTransforms` itself (keeping a still joint's fields): the bytes must
    be the SDK's, whichever joints move, stand still, sit at zero (either sign) or were never
    heard of, at any time stamp."""
    # (a long id makes each transform longer than 127 bytes: a two-byte length)
    twins = [Twin("arm", MODEL), Twin("a-robot-with-a-rather-long-name-" + "x" * 40, MODEL)]
    rng = random.Random(11)
    heard: dict[tuple[str, str], dict[str, float]] = {}
    stamps = [0, 1, 999_999_999, 1_000_000_000, 1_700_000_000_123_456_789, (1 << 32) - 1]
    for step in range(1200):
        twin = twins[step % 2]
        tree = rng.choice(["virtual", "real"])
        moved = {
            name: rng.choice([0.0, -0.0, 90.0, rng.uniform(-180.0, 180.0)])
            for name in SPECS
            if rng.random() < 0.3
        }
        twin.update(tree, moved)
        heard.setdefault((twin.robot_id, tree), {}).update(moved)
        ns = stamps[step % len(stamps)] if step % 3 else rng.randrange(1 << 62)
        ns %= (1 << 32) * 1_000_000_000  # the SDK's Timestamp holds 32-bit seconds
        ours = twin.encode_tree(tree, ns)
        assert ours == sdk_tree(twin, tree, heard[twin.robot_id, tree], ns), (step, moved)
        decoded = decode("foxglove.FrameTransforms", ours)
        assert len(decoded.transforms) == len(twin.kinematics.joints) + 1


@pytest.fixture
async def foxglove_file(autojump_clock: MockClock, tmp_path: Path) -> AsyncIterator[Path]:
    """A session recorded with a transform for every targets and joint-states record."""
    (path,) = await record_scenario(tmp_path, session_scenario, foxglove_rate=0.0)
    yield path


def read_views(path: Path) -> list[tuple[str, str, Any, int]]:
    """(topic, schema name, decoded message, log time) of every Foxglove message in a file;
    each channel's schema must be the one the SDK ships."""
    found = []
    with open(path, "rb") as stream:
        for schema, channel, message in make_reader(stream).iter_messages():
            if schema is None or schema.encoding != "protobuf":
                continue
            assert schema.name in SDK_TYPES and channel.message_encoding == "protobuf"
            assert schema.data == shipped_schema(schema.name)
            decoded = decode(schema.name, message.data)
            found.append((channel.topic, schema.name, decoded, message.log_time))
    return found


async def test_recordings_carry_transforms_model_and_log(
    autojump_clock: MockClock, foxglove_file: Path
) -> None:
    views = read_views(foxglove_file)
    recording = read_recording(foxglove_file)
    topics = {view[0] for view in views}
    assert topics == {"/robots/arm/tf", "/robots/arm/scene", "/robots/arm/log"}
    assert recording.foreign_topics == 0  # Foxglove's topics are Arena's own

    # one transform message per targets and per joint states record, at the same log time
    records = [m for m in recording.messages if m.kind in ("targets", "joint_states")]
    transforms = [view for view in views if view[0] == "/robots/arm/tf"]
    assert len(transforms) == len(records) > 100
    kinematics = Kinematics.from_urdf(MODEL.urdf_path)
    for record, (_, _, message, log_time) in zip(records, transforms, strict=True):
        assert log_time == record.log_time
        tree = "virtual" if record.kind == "targets" else "real"
        frames = {(t.parent_frame_id, t.child_frame_id): t for t in message.transforms}
        assert ("world", f"arm/{tree}/base") in frames
        values = {SPECS[n].urdf_name: SPECS[n].to_urdf(v) for n, v in record.data["joints"].items()}
        for joint, (rotation, translation) in kinematics.joint_transforms(values):
            sent = frames[(f"arm/{tree}/{joint.parent}", f"arm/{tree}/{joint.child}")]
            assert sent.timestamp.seconds * 10**9 + sent.timestamp.nanos == log_time
            got = (sent.rotation.x, sent.rotation.y, sent.rotation.z, sent.rotation.w)
            assert np.allclose(got, rotation, atol=1e-9)
            moved = (sent.translation.x, sent.translation.y, sent.translation.z)
            assert np.allclose(moved, translation)

    # the model: every link's meshes, embedded, on the real tree; a skeleton on the virtual one
    (scene,) = [view[2] for view in views if view[0] == "/robots/arm/scene"]
    meshes = {e.frame_id: e.models for e in scene.entities if e.models}
    expected: dict[str, list[Any]] = {}
    for visual in visuals(MODEL.urdf_path):
        expected.setdefault(f"arm/real/{visual.link}", []).append(stl_vertices(visual.path))
    assert meshes.keys() == expected.keys()
    for frame, models in meshes.items():
        assert all(m.media_type == "model/gltf-binary" for m in models)
        shown = [foxglove_turn(glb_triangles(m.data)) for m in models]
        assert len(shown) == len(expected[frame])
        assert all(np.array_equal(a, b) for a, b in zip(shown, expected[frame], strict=True))
    skeleton = {e.frame_id for e in scene.entities if e.lines}
    assert skeleton == {f"arm/virtual/{j.parent}" for j in kinematics.joints}
    assert all(e.frame_locked for e in scene.entities)

    # the log: the e-stop as an error, the refused command as a warning, the reset
    lines = [(view[2].level, view[2].message) for view in views if view[0] == "/robots/arm/log"]
    error, warning = (
        foxglove.messages.LogLevel.Error.value,
        foxglove.messages.LogLevel.Warning.value,
    )
    assert (error, "E-STOP: test stop") in lines
    assert any(level == warning and "refused ESTOPPED" in text for level, text in lines)
    assert any("state idle" in text and "Reset" in text for _, text in lines)


async def test_transforms_at_a_capped_rate_still_end_on_the_newest_pose(
    autojump_clock: MockClock, tmp_path: Path
) -> None:
    (path,) = await record_scenario(tmp_path, session_scenario)  # 30 a second per tree
    recording = read_recording(path)
    transforms = [v for v in read_views(path) if v[0] == "/robots/arm/tf"]
    for kind, tree in (("targets", "virtual"), ("joint_states", "real")):
        records = {m.log_time: m for m in recording.messages if m.kind == kind}
        sent = [
            (log_time, message)
            for _, _, message, log_time in transforms
            if any(t.child_frame_id == f"arm/{tree}/base" for t in message.transforms)
        ]
        assert 10 < len(sent) < len(records)  # held back, not dropped altogether
        assert all(log_time in records for log_time, _ in sent)  # each at a record's time
        assert max(records) == sent[-1][0]  # the last pose is always there
        # spaced at least 1/30 s, but where a batch ended and its newest pose was added
        gaps = [b[0] - a[0] for a, b in itertools.pairwise(sent)]
        assert sum(gap < 1e9 / 30 for gap in gaps) < len(gaps) / 2


async def test_recover_keeps_the_view_and_it_can_be_left_out(
    autojump_clock: MockClock, foxglove_file: Path, tmp_path: Path
) -> None:
    copy = tmp_path / "copy.mcap"
    write_recording(read_recording(foxglove_file), copy)
    assert [(v[0], v[3]) for v in read_views(copy)] == [
        (v[0], v[3]) for v in read_views(foxglove_file)
    ]
    (plain,) = await record_scenario(tmp_path / "plain", session_scenario, foxglove=False)
    assert read_views(plain) == []
    assert len(read_recording(plain).messages) == len(read_recording(foxglove_file).messages)


async def test_layout_shows_the_recorded_robots(
    autojump_clock: MockClock, foxglove_file: Path, tmp_path: Path
) -> None:
    output = tmp_path / "layout.json"
    assert cli.main(["foxglove-layout", "--recording", str(foxglove_file), "-o", str(output)]) == 0
    layout = json.loads(output.read_text())
    panels: list[dict[str, Any]] = []

    def walk(node: dict[str, Any]) -> None:
        if node.get("type") == "panel":
            panels.append(node)
        for item in node.get("items", []):
            walk(item["content"])

    walk(layout["content"])
    kinds = [panel["panelType"] for panel in panels]
    assert kinds.count("ThreeDee") == 1 and kinds.count("Log") == 1
    assert kinds.count("Plot") == len(MODEL.joints)
    recorded = {m.topic for m in read_recording(foxglove_file).messages}
    three_d = next(p for p in panels if p["panelType"] == "ThreeDee")
    assert set(three_d["config"]["topics"]) == {"/robots/arm/scene"}
    assert three_d["config"]["scene"]["meshUpAxis"] == "z_up"  # URDF meshes are Z-up
    for panel in panels:
        for series in panel["config"].get("paths", []):
            topic, _, path = series["value"].partition(".")
            assert topic in recorded and path.startswith("joints.")


def test_the_live_server_stays_on_loopback() -> None:
    with pytest.raises(ArenaError) as refused:
        ServerConfig(host="0.0.0.0", api_keys=("k",), foxglove_port=0).check()
    assert refused.value.code == ErrorCode.INVALID_CONFIG and "loopback" in refused.value.message
    ServerConfig(host="::1", foxglove_port=0).check()


def listening_addresses(port: int) -> set[str]:
    """The local addresses of the TCP sockets listening on `port` (Linux: /proc/net/tcp and
    tcp6), as the kernel holds them (hex, e.g. 0100007F for 127.0.0.1)."""
    found = set()
    for table in (Path("/proc/net/tcp"), Path("/proc/net/tcp6")):
        if not table.exists():
            continue
        for line in table.read_text().splitlines()[1:]:
            fields = line.split()
            address, _, hex_port = fields[1].partition(":")
            if fields[3] == "0A" and int(hex_port, 16) == port:  # 0A: LISTEN
                found.add(address)
    return found


def outward_address() -> str | None:
    """An address of this machine that is not loopback, if it has one (a UDP socket's
    connect sends nothing: it only picks the route)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        try:
            probe.connect(("198.51.100.1", 9))  # TEST-NET-2: any route out will do
        except OSError:
            return None
        address = str(probe.getsockname()[0])
    return None if address.startswith("127.") else address


async def test_the_live_server_binds_loopback_alone(
    start_server: Callable[..., Awaitable[RunningServer]],
) -> None:
    server = await start_server(foxglove_port=0)
    assert server.app.foxglove is not None
    port = server.app.foxglove.port
    # it answers on loopback...
    url = f"ws://127.0.0.1:{port}"
    async with open_websocket_url(url, subprotocols=["foxglove.sdk.v1"]) as ws:
        assert ws.subprotocol == "foxglove.sdk.v1"
    # ...and listens there alone: the kernel's table, and a connection to this machine's
    # outward address refused
    if sys.platform == "linux":
        assert listening_addresses(port) == {"0100007F"}  # 127.0.0.1, and no wildcard
    outward = outward_address()
    if outward is not None:
        with pytest.raises(OSError):
            stream = await trio.open_tcp_stream(outward, port)
            await stream.aclose()
    assert sys.platform == "linux" or outward is not None, "nothing here could tell"


async def advertised(ws: WebSocketConnection, wanted: set[str]) -> dict[str, dict[str, Any]]:
    """Read the server's JSON messages until every wanted topic is advertised."""
    channels: dict[str, dict[str, Any]] = {}
    while not wanted <= set(channels):
        message = await ws.get_message()
        assert isinstance(message, str)
        parsed = json.loads(message)
        if parsed["op"] == "advertise":
            channels.update({c["topic"]: c for c in parsed["channels"]})
    return channels


class Subscriptions:
    """A Foxglove client's subscriptions, and the data they bring.

    foxglove-sdk (0.30, and its main branch) sends a channel's advertisement before it records
    the channel as known to the client, so a subscription sent the moment the advertisement
    arrives can be refused; the server says so in a status message ("Unknown channel ID: N").
    A refused subscription is sent again, as a client that reads its status messages would.
    """

    def __init__(self, ws: WebSocketConnection) -> None:
        self.ws = ws
        self.topics: dict[int, str] = {}  # subscription id -> topic
        self._requests: dict[int, dict[str, int]] = {}  # channel id -> its subscribe request

    async def add(self, channels: dict[str, dict[str, Any]]) -> None:
        """Subscribe to these advertised channels (topic -> advertisement)."""
        requests = []
        for topic, channel in channels.items():
            number = len(self.topics) + 1
            self.topics[number] = topic
            request = self._requests[channel["id"]] = {"id": number, "channelId": channel["id"]}
            requests.append(request)
        await self.ws.send_message(json.dumps({"op": "subscribe", "subscriptions": requests}))

    async def next_data(self) -> tuple[str, bytes]:
        """The next message of a subscription: (its topic, payload)."""
        while True:
            message = await self.ws.get_message()
            if isinstance(message, bytes):
                if message[0] == 0x01:
                    (number,) = struct.unpack_from("<I", message, 1)
                    return self.topics[number], message[13:]
                continue
            parsed = json.loads(message)
            refused = parsed["op"] == "status" and re.fullmatch(
                r"Unknown channel ID: (\d+)", parsed["message"]
            )
            if refused and int(refused.group(1)) in self._requests:
                request = self._requests[int(refused.group(1))]
                await self.ws.send_message(
                    json.dumps({"op": "subscribe", "subscriptions": [request]})
                )


async def test_live_foxglove_clients_see_twins_joints_and_stops(
    start_server: Callable[..., Awaitable[RunningServer]],
) -> None:
    server = await start_server(demo=True, foxglove_port=0)
    assert server.app.foxglove is not None
    port = server.app.foxglove.port
    topics = {f"/robots/demo-arm/{kind}" for kind in ("tf", "scene", "log", "joint_states")}
    url = f"ws://127.0.0.1:{port}"
    with trio.fail_after(60):  # only a broken bridge waits that long
        await watch_live(server, url, topics)


async def watch_live(server: RunningServer, url: str, topics: set[str]) -> None:
    """Subscribe as Foxglove does; see the model, the arm move and the e-stop."""
    assert server.app.foxglove is not None
    async with open_websocket_url(
        url, subprotocols=["foxglove.sdk.v1"], max_message_size=64 << 20
    ) as ws:
        assert ws.subprotocol == "foxglove.sdk.v1"
        channels = await advertised(ws, topics)
        for name, channel in channels.items():
            if channel["encoding"] == "protobuf":
                assert channel["schemaName"] in SDK_TYPES
                assert base64.b64decode(channel["schema"]) == shipped_schema(channel["schemaName"])
            else:
                assert name.endswith(("/targets", "/joint_states"))
                assert channel["encoding"] == "json"
        subscriptions = Subscriptions(ws)
        await subscriptions.add({name: channels[name] for name in topics})
        # a new subscriber gets the 3D model
        while (got := await subscriptions.next_data())[0] != "/robots/demo-arm/scene":
            pass
        scene = decode("foxglove.SceneUpdate", got[1])
        assert {e.frame_id for e in scene.entities if e.models} >= {"demo-arm/real/base"}

        async with server.client() as http:
            moved = await http.put(
                "/api/robots/demo-arm/joints", json={"joints": [{"name": "Rotation", "value": 30}]}
            )
            assert moved.status_code == 200
            # the real tree follows until Rotation reports 30 degrees
            rotation = MODEL.joint("Rotation")
            assert rotation is not None
            kinematics = Kinematics.from_urdf(MODEL.urdf_path)
            (joint,) = [j for j in kinematics.joints if j.name == rotation.urdf_name]
            expected = joint.transform(rotation.to_urdf(30.0))[0]
            reached = False
            while not reached:
                name, payload = await subscriptions.next_data()
                if name != "/robots/demo-arm/tf":
                    continue
                message = decode("foxglove.FrameTransforms", payload)
                for t in message.transforms:
                    if t.child_frame_id == f"demo-arm/real/{joint.child}":
                        got_q = (t.rotation.x, t.rotation.y, t.rotation.z, t.rotation.w)
                        reached = bool(np.allclose(got_q, expected, atol=1e-6))
            stopped = await http.post("/api/robots/demo-arm/estop", json={"reason": "fox test"})
            assert stopped.status_code == 200
        while True:
            name, payload = await subscriptions.next_data()
            if name == "/robots/demo-arm/log":
                line = decode("foxglove.Log", payload)
                if line.message == "E-STOP: fox test":
                    break
        assert server.app.foxglove.dropped == 0


async def test_live_foxglove_shows_each_camera_as_compressed_images(
    start_server: Callable[..., Awaitable[RunningServer]],
) -> None:
    server = await start_server(demo=True, foxglove_port=0)
    assert server.app.foxglove is not None
    async with server.client() as http:
        camera = {"name": "front", "source": "test-pattern", "width": 160, "height": 120}
        assert (await http.post("/api/robots/demo-arm/cameras", json=camera)).status_code == 201
    topic = "/robots/demo-arm/cameras/front"
    url = f"ws://127.0.0.1:{server.app.foxglove.port}"
    with trio.fail_after(60):  # only a broken bridge waits that long
        async with open_websocket_url(
            url, subprotocols=["foxglove.sdk.v1"], max_message_size=64 << 20
        ) as ws:
            channels = await advertised(ws, {topic})
            assert channels[topic]["schemaName"] == "foxglove.CompressedImage"
            assert base64.b64decode(channels[topic]["schema"]) == shipped_schema(
                "foxglove.CompressedImage"
            )
            subscriptions = Subscriptions(ws)
            await subscriptions.add({topic: channels[topic]})
            counters = []
            while len(counters) < 3:
                _, payload = await subscriptions.next_data()
                image = decode("foxglove.CompressedImage", payload)
                assert (image.format, image.frame_id) == ("jpeg", "demo-arm/cameras/front")
                counters.append(read_pattern_counter(jpeg_rgb(image.data)))
            assert counters == sorted(counters) and len(set(counters)) == 3
