"""One robot as a ROS 2 node: what it publishes, the commands it takes, its services.

The node `/<name>` (name: `wire.ros_name`) has, each with its liveliness token:

- publishers `/<name>/joint_states` (measured joints, URDF names and radians, stamped with
  the measurement's time, on every report and again every `REPEAT` s while none comes), `/tf`
  (the URDF's frames at the measured joints, prefixed `<name>/`) and `/<name>/robot_description`
  (the URDF, kept for late subscribers as robot_state_publisher's transient local QoS does);
- subscriptions `/<name>/joint_trajectory` and `/<name>/forward_position_controller/commands`:
  the publisher is a master like any other, claiming the robot with its first command;
- services `/<name>/estop` and `/<name>/reset` (std_srvs/srv/Trigger).
"""

from __future__ import annotations

import contextlib
import logging
import time
from collections.abc import Awaitable, Callable
from functools import partial
from typing import TYPE_CHECKING, Any, Protocol

import trio

from arena.protocol.errors import ArenaError
from arena.robot.events import JointStatesReceived
from arena.robot.kinematics import Kinematics
from arena.robot.links import MasterLink
from arena.robot.motion import Command
from arena.robot.safety import Mode, Refused
from arena.ros2 import messages, wire

if TYPE_CHECKING:
    from arena.robot.handle import Robot


class Graph(Protocol):
    """What a node needs of the bridge (`arena.ros2.bridge.Ros2Bridge`)."""

    domain: int
    session: Any
    session_id: str

    def new_entity_id(self) -> int:
        """A fresh entity id of the session."""

    def from_zenoh(self, handler: Callable[[Any], Any]) -> Callable[[Any], None]:
        """A Zenoh callback that hands its argument to `handler` in trio."""


log = logging.getLogger(__name__)

#: Seconds between joint states while no report comes (10 Hz at rest).
REPEAT = 0.1
#: Service calls of one node answered at once; more are answered "busy" at once.
MAX_CALLS = 8
#: Seconds between two warnings of one node (the others are counted, then said).
WARN_EVERY = 1.0
#: Publishers whose refused claim a node remembers (the oldest forgotten first): a GID is
#: whatever a sample's attachment says, so a peer could make up any number of them.
MAX_REFUSED = 64


class RobotNode:
    """A robot's ROS 2 node on the bridge's session. `run` serves it until the robot stops."""

    def __init__(self, bridge: Graph, robot: Robot, name: str, node_id: int) -> None:
        self.bridge = bridge
        self.robot = robot
        self.name = name
        self.node_id = node_id
        model = robot.model
        self.kinematics = Kinematics.from_urdf(model.urdf_path)
        self.by_urdf = {joint.urdf_name: joint for joint in model.joints}
        #: ROS publishers (by GID) that command this robot, with their master link.
        self.masters: dict[bytes, MasterLink] = {}
        self.tokens: list[str] = []  # the node's own tokens' keys (tests and logs)
        self._entities: list[Any] = []
        self._publishers: dict[str, tuple[Any, bytes]] = {}  # topic -> (publisher, gid)
        self._sequence = 0
        self._playing: trio.CancelScope | None = None
        # The newest command not yet handled (latest wins: a command stream never queues up).
        self._pending: tuple[Callable[[Any], Awaitable[None]], Any] | None = None
        self._wake = trio.Event()
        #: Commands a newer one replaced before they were handled.
        self.superseded = 0
        #: Publishers refused the robot, with its master and state then and the refusal.
        self._refusals: dict[bytes, tuple[tuple[str | None, str], ArenaError]] = {}
        #: Commands dropped unasked because their publisher was refused as things still are.
        self.refused_again = 0
        self._calls = 0  # service calls being answered
        self._nursery: trio.Nursery | None = None
        self._warned_at = -WARN_EVERY
        self._unsaid = 0

    # -- the graph -------------------------------------------------------------------------------

    def topic(self, suffix: str) -> str:
        """A topic or service of this node: `/<name>/<suffix>`."""
        return f"/{self.name}/{suffix}"

    def _entity(self, kind: str, topic: str = "", ros_type: str = "", qos: str = "") -> wire.Entity:
        bridge = self.bridge
        return wire.Entity(
            bridge.domain,
            bridge.session_id,
            self.node_id,
            self.node_id if kind == wire.NODE else bridge.new_entity_id(),
            kind,
            self.name,
            "/",
            topic,
            ros_type,
            messages.type_hash(ros_type) if ros_type else "",
            qos or wire.QOS_DEPTH_10,
        )

    def _declare(self, entity: wire.Entity) -> str:
        token = entity.token()
        self._entities.append(self.bridge.session.liveliness().declare_token(token))
        self.tokens.append(token)
        return token

    def _key(self, entity: wire.Entity) -> str:
        return wire.data_key(self.bridge.domain, entity.topic, entity.ros_type, entity.type_hash)

    def _publish_on(self, topic: str, ros_type: str, qos: str = "") -> wire.Entity:
        entity = self._entity(wire.PUBLISHER, topic, ros_type, qos)
        self._publishers[topic] = (
            self.bridge.session.declare_publisher(self._key(entity)),
            entity.gid(),
        )
        self._declare(entity)
        return entity

    def declare(self) -> None:
        """Every entity of the node, with its token."""
        import zenoh.ext

        session, bridge = self.bridge.session, self.bridge
        self._declare(self._entity(wire.NODE))
        self._publish_on(self.topic("joint_states"), messages.JOINT_STATE)
        self._publish_on("/tf", messages.TF_MESSAGE, wire.QOS_DEPTH_100)
        described = self._entity(
            wire.PUBLISHER,
            self.topic("robot_description"),
            messages.STRING,
            wire.QOS_TRANSIENT_LOCAL,
        )
        cached = zenoh.ext.declare_advanced_publisher(
            session,
            self._key(described),
            cache=zenoh.ext.CacheConfig(max_samples=1),
            publisher_detection=True,
        )
        self._entities.append(cached)
        self._declare(described)
        urdf = self.robot.model.urdf_path.read_text(encoding="utf-8")
        cached.put(messages.string(urdf), attachment=self._attachment(described.gid()))
        for suffix, ros_type, handler in (
            ("joint_trajectory", messages.TRAJECTORY, self._trajectory),
            ("forward_position_controller/commands", messages.FLOAT64_ARRAY, self._positions),
        ):
            entity = self._entity(wire.SUBSCRIPTION, self.topic(suffix), ros_type)
            self._entities.append(
                session.declare_subscriber(
                    self._key(entity), bridge.from_zenoh(partial(self._take, handler))
                )
            )
            self._declare(entity)
        services: tuple[tuple[str, Callable[[Any], Awaitable[None]]], ...] = (
            ("estop", self._estop),
            ("reset", self._reset),
        )
        for suffix, serve in services:
            entity = self._entity(wire.SERVICE, self.topic(suffix), messages.TRIGGER)
            self._entities.append(
                session.declare_queryable(
                    self._key(entity), bridge.from_zenoh(partial(self._call, serve)), complete=True
                )
            )
            self._declare(entity)

    def undeclare(self) -> None:
        """Every entity and token goes (the robot is gone)."""
        for entity in [*self._entities, *(p for p, _ in self._publishers.values())]:
            with contextlib.suppress(Exception):
                entity.undeclare()
        self._entities.clear()
        self._publishers.clear()

    def _attachment(self, gid: bytes) -> bytes:
        self._sequence += 1
        return wire.attachment(self._sequence, time.time_ns(), gid)

    # -- publishing --------------------------------------------------------------------------------

    async def run(self) -> None:
        """Serve the node until the robot stops, then leave the graph."""
        self.declare()
        try:
            async with trio.open_nursery() as nursery:
                self._nursery = nursery
                nursery.start_soon(self._commands)
                await self._publishing()
                nursery.cancel_scope.cancel()
        finally:
            self.undeclare()

    async def _publishing(self) -> None:
        """Publish the measured joints until the robot stops."""
        robot = self.robot
        with robot.subscribe(maxlen=256, kinds=[JointStatesReceived]) as events:
            degrees = dict(robot.joint_values()[1])
            stamp = time.time_ns()
            while True:
                if degrees:
                    self.publish(degrees, stamp)
                with trio.move_on_after(REPEAT):
                    try:
                        event = await events.get()
                    except trio.EndOfChannel:
                        return
                    for later in [event, *events.drain()]:
                        assert isinstance(later, JointStatesReceived)
                        degrees.update(later.joints)
                        stamp = int(later.wall_time * 1e9)

    def publish(self, degrees: dict[str, float], stamp: int) -> None:
        """Joint states and /tf for joints at `degrees` (wire units by joint name)."""
        names, positions, radians = [], [], {}
        for joint in self.robot.model.joints:
            value = degrees.get(joint.name)
            if value is None:
                continue
            names.append(joint.urdf_name)
            positions.append(joint.to_urdf(value))
            radians[joint.urdf_name] = positions[-1]
        publisher, gid = self._publishers[self.topic("joint_states")]
        publisher.put(
            messages.joint_state(stamp, names, positions), attachment=self._attachment(gid)
        )
        prefix = self.name
        frames = [
            (f"{prefix}/{joint.parent}", f"{prefix}/{joint.child}", pose)
            for joint, pose in self.kinematics.joint_transforms(radians)
        ]
        publisher, gid = self._publishers["/tf"]
        publisher.put(messages.transforms(stamp, frames), attachment=self._attachment(gid))

    # -- commands ----------------------------------------------------------------------------------

    def _take(self, handler: Callable[[Any], Awaitable[None]], sample: Any) -> None:
        """In trio, from a subscription: keep the newest command for `_commands` (one that
        waited is replaced and counted, as latest wins toward a robot)."""
        if self._pending is not None:
            self.superseded += 1
        self._pending = (handler, sample)
        self._wake.set()

    async def _commands(self) -> None:
        """Handle the commands, one at a time, the newest first."""
        while True:
            await self._wake.wait()
            self._wake = trio.Event()
            if self._pending is None:
                continue
            handler, sample = self._pending
            self._pending = None
            await handler(sample)
            del sample

    def warn(self, text: str, *args: Any) -> None:
        """Log a warning about what a ROS peer sent, at most one a `WARN_EVERY` (a flood of
        bad commands is said as a count, never as a flood of lines)."""
        now = trio.current_time()
        if now - self._warned_at < WARN_EVERY:
            self._unsaid += 1
            return
        if self._unsaid:
            text += f" (and {self._unsaid} more since the last warning)"
        self._warned_at, self._unsaid = now, 0
        log.warning("ros2: %s: " + text, self.robot.robot_id, *args)

    def commands_from(self, gid: bytes) -> bool:
        """True if the publisher `gid` has commanded this robot."""
        return gid in self.masters

    async def publisher_gone(self, gid: bytes, topic: str) -> None:
        """A commanding publisher's token went: its master is lost (the robot's loss policy
        applies: an e-stop by default)."""
        self._refusals.pop(gid, None)
        link = self.masters.pop(gid, None)
        if link is None:
            return
        if self._playing is not None:
            self._playing.cancel()
        log.warning("ros2: %s: the publisher on %s is gone", self.robot.robot_id, topic)
        with contextlib.suppress(ArenaError):
            await link.lost(f"ROS 2 publisher on {topic} gone (liveliness token lost)")

    async def _master(self, sample: Any, topic: str) -> MasterLink | None:
        """The master link of the sample's publisher: claimed with its first command; None
        when refused (the actor logs and records the refusal with its code). A publisher
        refused is not asked for again while the robot's master and state are as they were
        then: its refusal is recorded once, not at the rate it publishes."""
        try:
            gid = wire.read_attachment(bytes(sample.attachment.to_bytes()))[2]
        except (AttributeError, ValueError) as exc:
            self.warn("%s: a command without rmw_zenoh's attachment: %s", topic, exc)
            return None
        link = self.masters.get(gid)
        if link is not None and not link.detached.is_set():
            return link
        snapshot = self.robot.snapshot()
        standing = (snapshot.owner, str(snapshot.mode))
        refused = self._refusals.get(gid)
        if refused is not None and refused[0] == standing:
            self.refused_again += 1
            self.warn("%s refused: %s", topic, refused[1].message)
            return None
        try:
            link = await self.robot.connect_master(
                f"ros2-{self.name}-{gid.hex()[:12]}",
                kind="ros2",
                description=f"ROS 2 publisher on {topic}",
            )
        except ArenaError as error:
            self.warn("%s refused: %s", topic, error.message)
            self._refusals.pop(gid, None)
            if len(self._refusals) >= MAX_REFUSED:
                del self._refusals[next(iter(self._refusals))]
            self._refusals[gid] = (standing, error)
            return None
        self._refusals.pop(gid, None)
        # One robot has one master: links of publishers that lost it are let go.
        self.masters = {g: m for g, m in self.masters.items() if not m.detached.is_set()}
        self.masters[gid] = link
        return link

    def _degrees(self, urdf: dict[str, float], topic: str) -> dict[str, float] | None:
        values = {}
        for name, value in urdf.items():
            joint = self.by_urdf.get(name)
            if joint is None:
                self.warn("%s: no joint %r (joints: %s)", topic, name, list(self.by_urdf))
                return None
            values[joint.name] = joint.from_urdf(value)
        return values

    async def _positions(self, sample: Any) -> None:
        topic = self.topic("forward_position_controller/commands")
        try:
            values = messages.read_positions(bytes(sample.payload.to_bytes()))
        except ValueError as exc:
            self.warn("%s: %s", topic, exc)
            return
        joints = self.robot.model.joints
        if len(values) != len(joints):
            self.warn("%s: %d values for %d joints", topic, len(values), len(joints))
            return
        degrees = self._degrees(
            {j.urdf_name: v for j, v in zip(joints, values, strict=True)}, topic
        )
        if degrees is None:
            return
        link = await self._master(sample, topic)
        if link is None:
            return
        if self._playing is not None:  # the newest command wins over a trajectory
            self._playing.cancel()
        self._refused(await link.command(Command.of(degrees)), topic)

    async def _trajectory(self, sample: Any) -> None:
        topic = self.topic("joint_trajectory")
        try:
            points = messages.read_trajectory(bytes(sample.payload.to_bytes()))
        except ValueError as exc:
            self.warn("%s: %s", topic, exc)
            return
        goals = [self._degrees(point.positions, topic) for point in points]
        if any(goal is None for goal in goals):
            return
        link = await self._master(sample, topic)
        if link is None or self._nursery is None:
            return
        if self._playing is not None:  # a new trajectory replaces the one playing
            self._playing.cancel()
        self._playing = trio.CancelScope()
        plan = [(p.at, g) for p, g in zip(points, goals, strict=True) if g is not None]
        self._nursery.start_soon(self._play, link, plan, self._playing)

    async def _play(
        self, link: MasterLink, plan: list[tuple[float, dict[str, float]]], scope: trio.CancelScope
    ) -> None:
        """Each point is a command sent when the point before it is due, lasting until its
        own time: the arm is at each point at its `time_from_start`."""
        topic = self.topic("joint_trajectory")
        with scope:
            start, previous = trio.current_time(), 0.0
            for at, goal in plan:
                await trio.sleep_until(start + previous)
                duration = at - previous
                result = await link.command(Command.of(goal, duration if duration > 0 else None))
                if self._refused(result, topic):
                    break
                previous = at
        if self._playing is scope:
            self._playing = None

    def _refused(self, result: Any, topic: str) -> bool:
        if result.accepted:
            return False
        self.warn("%s: command refused (%s): %s", topic, result.code, result.message)
        return True

    # -- services ----------------------------------------------------------------------------------

    def _call(self, serve: Callable[[Any], Awaitable[None]], query: Any) -> Awaitable[None] | None:
        """In trio, from a queryable: the call answered in a task of its own, or "busy" at
        once when `MAX_CALLS` are being answered already."""
        if self._calls >= MAX_CALLS:
            self._answer(query, False, "busy: too many calls at once, try again")
            return None
        self._calls += 1
        return self._counted(serve(query))

    async def _counted(self, call: Awaitable[None]) -> None:
        try:
            await call
        finally:
            self._calls -= 1

    async def _estop(self, query: Any) -> None:
        await self.robot.estop(f"ROS 2 service {self.topic('estop')}")
        mode = self.robot.snapshot().mode
        done = mode == Mode.ESTOPPED
        self._answer(query, done, "e-stopped" if done else f"not e-stopped: {mode}")

    async def _reset(self, query: Any) -> None:
        outcome = await self.robot.reset()
        mode = self.robot.snapshot().mode
        done = mode != Mode.ESTOPPED
        reason = outcome.message if isinstance(outcome, Refused) else ""
        self._answer(query, done, f"reset: {mode}" if done else f"still e-stopped: {reason}")

    def _answer(self, query: Any, success: bool, message: str) -> None:
        """Reply with the caller's sequence number and GID in the attachment."""
        try:
            sequence, _, gid = wire.read_attachment(bytes(query.attachment.to_bytes()))
        except (AttributeError, ValueError):
            sequence, gid = 0, bytes(wire.GID_SIZE)
        with contextlib.suppress(Exception):  # the caller may have given up
            query.reply(
                query.key_expr,
                messages.trigger_response(success, message),
                attachment=wire.attachment(sequence, time.time_ns(), gid),
            )
        del query
