"""ROS 2 over Zenoh: Arena's robots as rmw_zenoh nodes (specs/ros2.md).

The peer on the other side is not Arena's code: plain eclipse-zenoh, rosbags' CDR codec and
rmw_zenoh's documented key expressions, attachment and tokens written out here by hand. It
connects to the server's session on 127.0.0.1 (port 0, multicast off). Waits are for samples
and events, bounded only so that a broken test ends.
"""

from __future__ import annotations

import json
import struct
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import trio

from arena.cli import main
from arena.recording.mcap_file import read_recording
from arena.robot.events import CommandHandled, PeerChanged, StateChanged
from arena.robot.model import load_robot_model
from arena.robot.safety import Mode
from tests.conftest import RunningServer, need

need("rosbags", "ros2")
zenoh = need("zenoh", "ros2")
xxhash = need("xxhash", "ros2")

from rosbags.typesys import Stores, get_typestore  # noqa: E402

from arena.ros2 import messages, wire  # noqa: E402

TYPES = get_typestore(Stores.ROS2_JAZZY)
#: rmw_zenoh's docs/design.md, "Topic and Service name mapping" and "Graph Cache".
CHATTER_HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
#: std_srvs/srv/Trigger's type hash as a ROS 2 Jazzy system publishes it.
TRIGGER_HASH = "RIHS01_eeff2cd6fa5ad9d27cdf4dec64818317839b62f212a91e6b5304b634b2062c5f"
STATES_KEY = "0/demo_arm/joint_states/sensor_msgs::msg::dds_::JointState_/" + TYPES.hash_rihs01(
    "sensor_msgs/msg/JointState"
)
TF_KEY = "0/tf/tf2_msgs::msg::dds_::TFMessage_/" + TYPES.hash_rihs01("tf2_msgs/msg/TFMessage")
DESCRIPTION_KEY = "0/demo_arm/robot_description/std_msgs::msg::dds_::String_/" + CHATTER_HASH
COMMANDS = "demo_arm/forward_position_controller/commands"
COMMANDS_KEY = f"0/{COMMANDS}/std_msgs::msg::dds_::Float64MultiArray_/" + TYPES.hash_rihs01(
    "std_msgs/msg/Float64MultiArray"
)
TRAJECTORY_KEY = (
    "0/demo_arm/joint_trajectory/trajectory_msgs::msg::dds_::JointTrajectory_/"
    + TYPES.hash_rihs01("trajectory_msgs/msg/JointTrajectory")
)
ESTOP_KEY = "0/demo_arm/estop/std_srvs::srv::dds_::Trigger_/" + TRIGGER_HASH
RESET_KEY = "0/demo_arm/reset/std_srvs::srv::dds_::Trigger_/" + TRIGGER_HASH


def test_key_expressions_tokens_and_attachment_are_rmw_zenohs() -> None:
    string_hash = messages.type_hash("std_msgs/msg/String")
    assert string_hash == CHATTER_HASH
    assert messages.type_hash(messages.TRIGGER) == TRIGGER_HASH
    assert wire.data_key(0, "/robot1/chatter", "std_msgs/msg/String", string_hash) == (
        "0/robot1/chatter/std_msgs::msg::dds_::String_/" + CHATTER_HASH
    )
    talker = wire.Entity(
        2, "8b20917502ee955ac4476e0266340d5c", 0, 10, wire.PUBLISHER, "talker", "/",
        "/chatter", "std_msgs/msg/String", string_hash, "::,7:,:,:,,",
    )  # fmt: skip
    assert talker.token() == (
        "@ros2_lv/2/8b20917502ee955ac4476e0266340d5c/0/10/MP/%/%/talker/%chatter/"
        f"std_msgs::msg::dds_::String_/{CHATTER_HASH}/::,7:,:,:,,"
    )
    node = wire.Entity(2, "aac3178e146ba6f1fc6e6a4085e77f21", 0, 0, wire.NODE, "listener")
    assert node.token() == "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/0/NN/%/%/listener"
    assert wire.token_topic(talker.token()) == ("MP", "/chatter")
    assert talker.gid() == xxhash.xxh3_128_intdigest(talker.token().encode()).to_bytes(16, "little")
    gid = bytes(range(16))
    golden = bytes([7, 0, 0, 0, 0, 0, 0, 0]) + (10**18).to_bytes(8, "little") + b"\x10" + gid
    assert wire.attachment(7, 10**18, gid) == golden
    assert wire.read_attachment(golden) == (7, 10**18, gid)
    for bad in (golden[:-1], golden[:16] + b"\x08" + gid):
        try:
            wire.read_attachment(bad)
        except ValueError:
            continue
        raise AssertionError(f"accepted {bad!r}")


def test_a_joint_state_is_cdr_that_rosbags_reads() -> None:
    data = messages.joint_state(1_700_000_000_123_456_789, ["a", "b"], [0.5, -1.25])
    assert data[:4] == b"\x00\x01\x00\x00"  # CDR, little-endian
    assert data[4:12] == struct.pack("<iI", 1_700_000_000, 123_456_789)
    decoded = TYPES.deserialize_cdr(data, "sensor_msgs/msg/JointState")
    assert decoded.name == ["a", "b"]
    assert list(decoded.position) == [0.5, -1.25]
    assert (decoded.header.stamp.sec, decoded.header.stamp.nanosec) == (1_700_000_000, 123_456_789)


def test_robot_ids_become_ros_names_by_one_rule() -> None:
    assert wire.ros_name("demo-arm") == "demo_arm"
    assert wire.ros_name("arm.left--2") == "arm_left_2"
    assert wire.ros_name("3arm") == "r_3arm"
    assert wire.ros_name("bras-é") == "bras_"
    book = wire.NameBook()
    assert book.take("demo-arm") == "demo_arm"
    assert book.take("demo_arm") == "demo_arm_2"
    assert book.take("demo.arm") == "demo_arm_3"
    book.release("demo-arm")
    assert book.take("demo--arm") == "demo_arm"


class Peer:
    """A ROS 2 peer: a Zenoh session whose callbacks hand samples to trio."""

    def __init__(self, session: Any) -> None:
        self.session = session
        self.zid = str(session.info.zid())
        self.token = trio.lowlevel.current_trio_token()

    def channel(self) -> tuple[Callable[[Any], None], trio.MemoryReceiveChannel[Any]]:
        send, receive = trio.open_memory_channel[Any](10_000)

        def callback(sample: Any) -> None:
            item = (
                str(sample.key_expr),
                str(sample.kind),
                None if sample.payload is None else bytes(sample.payload.to_bytes()),
            )
            self.token.run_sync_soon(send.send_nowait, item)

        return callback, receive

    def publisher(self, topic: str, ros_type: str) -> tuple[Any, Any, bytes]:
        """A publisher with its MP token, as rmw_zenoh declares them."""
        dds = "{}::{}::dds_::{}_".format(*ros_type.split("/"))
        token = (
            f"@ros2_lv/0/{self.zid}/0/5/MP/%/%/commander/%{topic.replace('/', '%')}/{dds}/"
            f"{TYPES.hash_rihs01(ros_type)}/::,10:,:,:,,"
        )
        gid = xxhash.xxh3_128_intdigest(token.encode()).to_bytes(16, "little")
        key = f"0/{topic}/{dds}/{TYPES.hash_rihs01(ros_type)}"
        return (
            self.session.declare_publisher(key),
            self.session.liveliness().declare_token(token),
            gid,
        )


async def next_state(receive: trio.MemoryReceiveChannel[Any]) -> Any:
    with trio.fail_after(20):
        _, _, data = await receive.receive()
    return TYPES.deserialize_cdr(data, "sensor_msgs/msg/JointState")


async def next_event(events: Any, kind: type[Any]) -> Any:
    """The robot's next event of type `kind`."""
    with trio.fail_after(20):
        while True:
            event = await events.get()
            if isinstance(event, kind):
                return event


async def states_until(receive: trio.MemoryReceiveChannel[Any], joint: str, value: float) -> Any:
    """Joint states until `joint` is within 0.01 rad of `value`."""
    while True:
        state = await next_state(receive)
        if abs(state.position[state.name.index(joint)] - value) < 0.01:
            return state


def call(session: Any, key: str, sequence: int) -> tuple[Any, tuple[int, int, bytes]]:
    """A Trigger call as rmw_zenoh's client makes it (in a thread: `get` blocks)."""
    # Trigger_Request is empty: the CDR header and rosidl's one padding byte.
    attachment = struct.pack("<qqB16s", sequence, time.time_ns(), 16, b"C" * 16)
    for reply in session.get(
        key, payload=b"\x00\x01\x00\x00\x00", attachment=attachment, timeout=10.0,
        target=zenoh.QueryTarget.ALL_COMPLETE,
    ):  # fmt: skip
        if reply.ok is not None:
            body = bytes(reply.ok.payload.to_bytes())
            answer = struct.unpack("<qqB16s", bytes(reply.ok.attachment.to_bytes()))
            return messages.store().deserialize_cdr(body, "std_srvs/srv/Trigger_Response"), (
                answer[0], answer[1], answer[3],
            )  # fmt: skip
    raise AssertionError(f"no answer on {key}")


def float64_array(values: list[float]) -> bytes:
    array = TYPES.types["std_msgs/msg/Float64MultiArray"]
    layout = TYPES.types["std_msgs/msg/MultiArrayLayout"](dim=[], data_offset=0)
    import numpy as np

    message = array(layout=layout, data=np.array(values, dtype=np.float64))
    return bytes(TYPES.serialize_cdr(message, "std_msgs/msg/Float64MultiArray"))


def trajectory(names: list[str], points: list[tuple[float, list[float]]]) -> bytes:
    import numpy as np

    types = TYPES.types
    header = types["std_msgs/msg/Header"](
        stamp=types["builtin_interfaces/msg/Time"](sec=0, nanosec=0), frame_id=""
    )
    empty = np.array([], dtype=np.float64)
    message = types["trajectory_msgs/msg/JointTrajectory"](
        header=header,
        joint_names=names,
        points=[
            types["trajectory_msgs/msg/JointTrajectoryPoint"](
                positions=np.array(values, dtype=np.float64),
                velocities=empty,
                accelerations=empty,
                effort=empty,
                time_from_start=types["builtin_interfaces/msg/Duration"](
                    sec=int(at), nanosec=round((at % 1) * 1e9)
                ),
            )
            for at, values in points
        ],
    )
    return bytes(TYPES.serialize_cdr(message, "trajectory_msgs/msg/JointTrajectory"))


async def test_a_ros2_peer_sees_reads_commands_and_stops_the_robot(start_server: Any) -> None:
    server: RunningServer = await start_server(
        demo=True, ros2=True, ros2_listen=("tcp/127.0.0.1:0",)
    )
    bridge = server.app.ros2
    locators = await bridge.locators()
    assert locators and locators[0].startswith("tcp/127.0.0.1:")
    config = zenoh.Config()
    config.insert_json5("mode", '"peer"')
    config.insert_json5("connect/endpoints", f'["{locators[0]}"]')
    config.insert_json5("scouting/multicast/enabled", "false")
    session = await trio.to_thread.run_sync(zenoh.open, config)
    robot = server.app.manager.get("demo-arm")
    joints = [j.urdf_name for j in robot.model.joints]
    try:
        peer = Peer(session)
        on_token, tokens = peer.channel()
        token_watch = session.liveliness().declare_subscriber(
            "@ros2_lv/0/**", on_token, history=True
        )
        arena_zid = bridge.session_id
        seen: set[str] = set()
        with trio.fail_after(20):
            while len(seen) < 8:  # the node, 3 publishers, 2 subscriptions, 2 services
                key, kind, _ = await tokens.receive()
                if kind.endswith("PUT") and f"/{arena_zid}/" in key:
                    seen.add(key)
        assert f"@ros2_lv/0/{arena_zid}/0/0/NN/%/%/demo_arm" in seen
        suffixes = {tuple(k.split("/")[5:10]) for k in seen if "/NN/" not in k}
        assert suffixes == {
            ("MP", "%", "%", "demo_arm", "%demo_arm%joint_states"),
            ("MP", "%", "%", "demo_arm", "%tf"),
            ("MP", "%", "%", "demo_arm", "%demo_arm%robot_description"),
            ("MS", "%", "%", "demo_arm", "%demo_arm%joint_trajectory"),
            ("MS", "%", "%", "demo_arm", f"%{COMMANDS.replace('/', '%')}"),
            ("SS", "%", "%", "demo_arm", "%demo_arm%estop"),
            ("SS", "%", "%", "demo_arm", "%demo_arm%reset"),
        }
        assert any(
            k.endswith(
                f"%demo_arm%robot_description/std_msgs::msg::dds_::String_/{CHATTER_HASH}/:1:,1:,:,:,,"
            )
            for k in seen
        )

        # Joint states at rest (>= 10 Hz with no report), URDF names, radians, rmw's attachment.
        on_state, states = peer.channel()
        subscriber = session.declare_subscriber(STATES_KEY, on_state)
        first = await next_state(states)
        assert first.name == joints
        real = robot.joint_values()[1]
        expected = [j.to_urdf(real[j.name]) for j in robot.model.joints]
        assert list(first.position) == expected
        second = await next_state(states)  # no report at rest: the same measurement again
        assert second.position.tolist() == first.position.tolist()
        assert second.header.stamp == first.header.stamp

        on_tf, tfs = peer.channel()
        tf_subscriber = session.declare_subscriber(TF_KEY, on_tf)
        with trio.fail_after(20):
            _, _, data = await tfs.receive()
        frames = TYPES.deserialize_cdr(data, "tf2_msgs/msg/TFMessage").transforms
        assert frames and all(f.child_frame_id.startswith("demo_arm/") for f in frames)
        assert all(f.header.frame_id.startswith("demo_arm/") for f in frames)

        # The URDF for a subscriber that joins late (rmw_zenoh's transient local).
        on_description, descriptions = peer.channel()
        late = zenoh.ext.declare_advanced_subscriber(
            session, DESCRIPTION_KEY, on_description,
            history=zenoh.ext.HistoryConfig(detect_late_publishers=True),
        )  # fmt: skip
        with trio.fail_after(20):
            _, _, data = await descriptions.receive()
        urdf = TYPES.deserialize_cdr(data, "std_msgs/msg/String").data
        assert urdf == robot.model.urdf_path.read_text(encoding="utf-8")

        # Commands: refused while another master holds the robot (the refusal an event the
        # recorder keeps, as any master's).
        publisher, publisher_token, gid = peer.publisher(COMMANDS, "std_msgs/msg/Float64MultiArray")

        def attached(sequence: int) -> bytes:
            return struct.pack("<qqB16s", sequence, time.time_ns(), 16, gid)

        other = await robot.connect_master("someone-else", kind="external")
        target = [0.2 + v if k == 0 else v for k, v in enumerate(expected)]
        kinds = [PeerChanged, StateChanged, CommandHandled]
        with robot.subscribe(kinds=kinds) as events:
            publisher.put(float64_array(target), attachment=attached(1))
            refusal = await next_event(events, PeerChanged)
            assert (refusal.kind, refusal.change) == ("ros2", "refused") and refusal.reason
            assert robot.snapshot().owner == "someone-else"
            await other.release()
            # Bad input changes nothing: not CDR, a value short, no attachment (no owner).
            publisher.put(b"\x00\x01\x00\x00garbage", attachment=attached(2))
            publisher.put(float64_array(target[:-1]), attachment=attached(3))
            publisher.put(float64_array(target))
            publisher.put(float64_array(target), attachment=attached(4))
            handled = await next_event(events, CommandHandled)
            owner = robot.snapshot().owner
            assert owner is not None and owner.startswith("ros2-") and handled.source == owner
            assert handled.result.accepted and handled.command.duration is None
            assert [g.value for g in handled.command.joints] == pytest.approx(
                [j.from_urdf(v) for j, v in zip(robot.model.joints, target, strict=True)]
            )
            moved = await states_until(states, joints[0], target[0])

            # A trajectory: each point a command due at its time, lasting until the next.
            names = [joints[0], joints[1]]
            start = list(moved.position[:2])
            points = [(0.2, [start[0] - 0.1, start[1]]), (0.5, [start[0] - 0.2, start[1] + 0.1])]
            traj = session.declare_publisher(TRAJECTORY_KEY)
            traj.put(trajectory(names, points), attachment=attached(5))
            specs = [robot.model.joint(robot.model.joints[k].name) for k in (0, 1)]
            for duration, (_, values) in zip((0.2, 0.3), points, strict=True):
                handled = await next_event(events, CommandHandled)
                assert handled.source == owner and handled.result.accepted
                assert handled.command.duration == pytest.approx(duration)
                assert [g.value for g in handled.command.joints] == pytest.approx(
                    [j.from_urdf(v) for j, v in zip(specs, values, strict=True)]  # type: ignore[union-attr]
                )
            await states_until(states, joints[0], start[0] - 0.2)

            # Its publisher's token goes: the master is lost, the robot e-stops.
            publisher_token.undeclare()
            with trio.fail_after(20):
                while robot.snapshot().mode != Mode.ESTOPPED:
                    await events.get()

        # Services: reset, then e-stop, each answered with the caller's sequence number.
        response, (sequence, _, client) = await trio.to_thread.run_sync(
            call, session, RESET_KEY, 41
        )
        assert response.success and (sequence, client) == (41, b"C" * 16)
        assert robot.snapshot().mode != Mode.ESTOPPED
        response, (sequence, _, _) = await trio.to_thread.run_sync(call, session, ESTOP_KEY, 42)
        assert response.success and sequence == 42
        assert robot.snapshot().mode == Mode.ESTOPPED

        # A robot deleted leaves the graph: its node's token goes.
        await server.app.manager.delete("demo-arm")
        node_token = f"@ros2_lv/0/{arena_zid}/0/0/NN/%/%/demo_arm"
        with trio.fail_after(20):
            while (await tokens.receive())[:2] != (node_token, "SampleKind.DELETE"):
                pass
        assert "demo-arm" not in bridge.nodes
        for entity in (late, tf_subscriber, subscriber, token_watch, publisher, traj):
            entity.undeclare()
    finally:
        await trio.to_thread.run_sync(session.close)


async def test_a_publisher_refused_while_a_websocket_master_drives_is_in_the_recording(
    start_server: Any, tmp_path: Path
) -> None:
    from mcap.reader import make_reader
    from trio_websocket import open_websocket_url

    from tests.test_server_ws import receive

    recordings = tmp_path / "recordings"
    server: RunningServer = await start_server(
        demo=True, ros2=True, ros2_listen=("tcp/127.0.0.1:0",), recordings_dir=str(recordings)
    )
    [locator, *_] = await server.app.ros2.locators()
    config = zenoh.Config()
    config.insert_json5("mode", '"peer"')
    config.insert_json5("connect/endpoints", f'["{locator}"]')
    config.insert_json5("scouting/multicast/enabled", "false")
    session = await trio.to_thread.run_sync(zenoh.open, config)
    robot = server.app.manager.get("demo-arm")
    try:
        publisher, token, gid = Peer(session).publisher(COMMANDS, "std_msgs/msg/Float64MultiArray")
        attachment = struct.pack("<qqB16s", 1, time.time_ns(), 16, gid)
        node = server.app.ros2.nodes["demo-arm"]

        async def send_until(done: Callable[[], bool]) -> None:
            """Commands until `done` (the first may go before the bridge hears the publisher)."""
            with trio.fail_after(20):
                while not done():
                    publisher.put(float64_array([0.0] * 6), attachment=attachment)
                    await trio.sleep(0.05)

        with robot.subscribe(kinds=[PeerChanged]) as events:
            async with open_websocket_url(f"{server.ws_url}/ws/master/demo-arm?id=driver") as ws:
                await receive(ws, "state")
                # Refused while the WebSocket master drives, as often as it sends: recorded once.
                await send_until(lambda: node.refused_again >= 3)
                assert robot.snapshot().owner == "driver"
                await ws.send_message(json.dumps({"type": "release"}))
                await receive(ws, "released")
                # The robot free, its next command claims it.
                await send_until(lambda: (robot.snapshot().owner or "").startswith("ros2-"))
            changes = [(e.kind, e.change, e.code) for e in events.drain()]
        assert changes == [
            ("websocket", "attached", None),
            ("ros2", "refused", "MASTER_ACTIVE"),
            ("websocket", "released", None),
            ("ros2", "attached", None),
        ]
        publisher.undeclare()
        token.undeclare()
    finally:
        await trio.to_thread.run_sync(session.close)
    server.stop.set()
    await server.done.wait()
    # Read back by the mcap library: the refusal, its code and who was refused.
    [path] = recordings.glob("*.mcap")
    with path.open("rb") as stream:
        peers = [
            json.loads(message.data)
            for _, channel, message in make_reader(stream).iter_messages()
            if channel.topic == "/robots/demo-arm/peer"
        ]
    refused = [p for p in peers if p["change"] == "refused"]
    assert len(refused) == 1, peers  # once, however many commands it sent meanwhile
    assert refused[0]["kind"] == "ros2" and refused[0]["peer_id"].startswith("ros2-demo_arm-")
    assert refused[0]["code"] == "MASTER_ACTIVE", refused[0]
    assert "driver" in refused[0]["reason"]


GOLDEN = Path(__file__).resolve().parent.parent / "recordings" / "golden" / "gentle-wave.mcap"


def test_a_recording_exports_as_a_ros2_bag_that_rosbags_reads(tmp_path: Path) -> None:
    from mcap.reader import make_reader
    from rosbags.rosbag2 import Reader

    out = tmp_path / "wave.mcap"
    assert main(["export", str(GOLDEN), "--format", "ros2", "-o", str(out)]) == 0
    recording = read_recording(GOLDEN)
    reports = [m for m in recording.messages if m.kind == "joint_states"]
    accepted = [m for m in recording.messages if m.kind == "command" and m.data["accepted"]]
    model = load_robot_model("so-arm100")
    with Reader(out) as bag:
        counts = {c.topic: (c.msgtype, c.msgcount) for c in bag.connections}
        assert counts == {
            "/arm/robot_description": ("std_msgs/msg/String", 1),
            "/arm/joint_states": ("sensor_msgs/msg/JointState", len(reports)),
            "/tf": ("tf2_msgs/msg/TFMessage", len(reports)),
            "/arm/joint_trajectory": ("trajectory_msgs/msg/JointTrajectory", len(accepted)),
        }
        states = [
            (stamp, TYPES.deserialize_cdr(data, "sensor_msgs/msg/JointState"))
            for connection, stamp, data in bag.messages()
            if connection.topic == "/arm/joint_states"
        ]
        commands = [
            TYPES.deserialize_cdr(data, connection.msgtype)
            for connection, _, data in bag.messages()
            if connection.topic == "/arm/joint_trajectory"
        ]
    last_report, (stamp, last) = reports[-1], states[-1]
    assert stamp == last_report.log_time
    assert last.name == [j.urdf_name for j in model.joints]
    for joint, value in zip(model.joints, last.position, strict=True):
        assert value == pytest.approx(joint.to_urdf(last_report.data["joints"][joint.name]))
    first = accepted[0].data
    point = commands[0].points[0]
    assert (
        point.time_from_start.sec + point.time_from_start.nanosec / 1e9 == first["duration"] / 1000
    )
    assert list(point.positions) == pytest.approx(
        [model.joint(j["name"]).to_urdf(j["value"]) for j in first["joints"]]  # type: ignore[union-attr]
    )
    with open(out, "rb") as stream:
        summary = make_reader(stream).get_summary()
    assert summary is not None
    assert {s.encoding for s in summary.schemas.values()} == {"ros2msg"}
    assert {c.message_encoding for c in summary.channels.values()} == {"cdr"}


def test_a_ros2_export_refuses_to_overwrite_or_to_guess_its_output(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "taken.mcap"
    out.write_bytes(b"mine")
    assert main(["export", str(GOLDEN), "--format", "ros2", "-o", str(out)]) == 2
    assert "exists already" in capsys.readouterr().err
    assert out.read_bytes() == b"mine"
    assert main(["export", str(GOLDEN), "--format", "ros2"]) == 2
    assert "needs -o" in capsys.readouterr().err
    assert main(["export", str(GOLDEN), "--format", "ros2", "-o", str(tmp_path / "x.bag")]) == 2
    assert ".mcap" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["taken.mcap"]


def test_ros2_settings_take_the_domain_from_the_environment_and_check_it(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    from arena.protocol.errors import ArenaError
    from arena.ros2.bridge import Ros2Settings
    from arena.server.config import ServerConfig, load_config

    monkeypatch.setenv("ROS_DOMAIN_ID", "7")
    assert ServerConfig(ros2=True).ros2_settings().domain == 7
    assert ServerConfig(ros2=True, ros_domain=3).ros2_settings().domain == 3
    assert load_config(None, {"ARENA_ROS_DOMAIN": "5", "ARENA_ROS2": "true"}).ros2_settings() == (
        Ros2Settings(5)
    )
    monkeypatch.setenv("ROS_DOMAIN_ID", "lab")
    for config, words in (
        (ServerConfig(ros2=True), "ROS_DOMAIN_ID is not a number"),
        (ServerConfig(ros2=True, ros_domain=233), "0-232"),
        (ServerConfig(ros2=True, ros_domain=0, ros2_connect=("localhost:7447",)), "endpoint"),
        (ServerConfig(ros2=True, ros_domain=0, ros2_listen=("tcp/0.0.0.0:7447",)), "--insecure"),
        (ServerConfig(ros2=True, ros_domain=0, ros2_connect=("tcp/10.0.0.2:7447",)), "10.0.0.2"),
    ):
        with pytest.raises(ArenaError, match=words):
            config.check()
    monkeypatch.delenv("ROS_DOMAIN_ID")
    assert ServerConfig(ros2=True).ros2_settings().domain == 0
    for endpoint in ("tcp/127.0.0.1:0", "tcp/[::1]:7447", "tcp/localhost:7447"):
        ServerConfig(ros2=True, ros2_listen=(endpoint,)).check()
    ServerConfig(ros2=True, ros2_listen=("tcp/0.0.0.0:7447",), insecure=True).check()
    # With no endpoint, where rmw_zenoh's nodes find their router.
    defaults = json_of(Ros2Settings().zenoh_config(), "connect/endpoints")
    assert defaults == ["tcp/localhost:7447"]
    assert (
        json_of(Ros2Settings(listen=("tcp/127.0.0.1:0",)).zenoh_config(), "connect/endpoints") == []
    )
    assert json_of(Ros2Settings().zenoh_config(), "scouting/multicast/enabled") is False


def json_of(config: Any, key: str) -> Any:
    import json

    return json.loads(config.get_json(key))
