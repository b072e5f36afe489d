"""Foxglove's view of a robot: its 3D model, the commanded and measured poses, and a log.

One `Twin` per robot turns robot events into Foxglove messages (protobuf, encoded by the
official `foxglove-sdk`, with the schemas it ships):
  /robots/{id}/tf     `foxglove.FrameTransforms`: two trees, `{id}/virtual/<link>` from the
                      targets sent to slaves and `{id}/real/<link>` from the joint states the
                      slaves report, each under `world`
  /robots/{id}/scene  `foxglove.SceneUpdate`: the URDF's meshes on the real tree (embedded as
                      glTF, `glb.py`) and a skeleton on the virtual one; sent once per file
                      and per viewer
  /robots/{id}/log    `foxglove.Log`: e-stops, resets, faults, refused commands and peers
The recording process and the live Foxglove server both use it, so a file and a live session
look the same.
"""

from __future__ import annotations

import functools
import struct
import sys
import xml.etree.ElementTree as ElementTree
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, get_args

from foxglove.messages import (
    Color,
    FrameTransforms,
    LinePrimitive,
    LinePrimitiveLineType,
    Log,
    LogLevel,
    ModelPrimitive,
    Point3,
    Pose,
    Quaternion,
    SceneEntity,
    SceneUpdate,
    Timestamp,
    Vector3,
)

from arena.protocol.errors import ArenaError
from arena.recording import glb
from arena.robot.events import (
    Audited,
    CommandHandled,
    EpisodeChanged,
    FaultReported,
    InterventionChanged,
    JointStatesReceived,
    MotionStopped,
    PeerChanged,
    PolicyInferred,
    RobotEvent,
    StateChanged,
    TargetsSent,
)
from arena.robot.kinematics import IDENTITY, Kinematics, UrdfJoint
from arena.robot.kinematics import Pose as KinematicPose
from arena.robot.meshes import visuals
from arena.robot.model import JointSpec, RobotModel, load_robot_model
from arena.robot.safety import Mode

#: Topic kind -> the Foxglove message type on it.
MESSAGE_TYPES: dict[str, Any] = {"tf": FrameTransforms, "scene": SceneUpdate, "log": Log}
#: The frame both trees of every robot hang from (the 3D panel's display frame).
WORLD = "world"
TREES = ("virtual", "real")

_MESH_COLOR = Color(r=0.93, g=0.55, b=0.18, a=1.0)
_SKELETON_COLOR = Color(r=0.2, g=0.55, b=1.0, a=0.9)
_LEVEL_OF_SEVERITY = {
    "info": LogLevel.Info,
    "warning": LogLevel.Warning,
    "error": LogLevel.Error,
    "critical": LogLevel.Fatal,
}


def schema(kind: str) -> tuple[str, str, bytes]:
    """(name, encoding, data) of the schema of a Foxglove topic kind."""
    found = MESSAGE_TYPES[kind].get_schema()
    return found.name, found.encoding, bytes(found.data)


def timestamp(ns: int) -> Timestamp:
    """A Foxglove timestamp from nanoseconds since the epoch."""
    return Timestamp(ns // 1_000_000_000, ns % 1_000_000_000)


class Twin:
    """Foxglove messages of one robot. Not thread-safe: one owner (the recording process's
    loop, or the live bridge's thread)."""

    def __init__(self, robot_id: str, model: RobotModel) -> None:
        self.robot_id = robot_id
        self.model = model
        self.kinematics = Kinematics.from_urdf(model.urdf_path)
        # Wire degrees of the joints last heard of, per tree (a partial update keeps the
        # rest), turned into URDF radians only when a tree is encoded: most updates are held
        # back by the rate, and a command stream makes thousands a second.
        self._degrees: dict[str, dict[str, float]] = {tree: {} for tree in TREES}
        self._slots: dict[str, list[_Slot]] = {}  # tree -> `_slots_of(tree)`

    def frame(self, tree: str, link: str) -> str:
        """The frame id of a link in one tree."""
        return f"{self.robot_id}/{tree}/{link}"

    def transforms(self, tree: str, joints: Mapping[str, float], ns: int) -> bytes:
        """The whole tree at joint values `joints` (wire degrees; missing joints keep their
        last value), as an encoded `FrameTransforms`."""
        self.update(tree, joints)
        return self.encode_tree(tree, ns)

    def update(self, tree: str, joints: Mapping[str, float]) -> None:
        """Note new joint values (wire degrees) of one tree without encoding anything."""
        self._degrees[tree].update(joints)

    def encode_tree(self, tree: str, ns: int) -> bytes:
        """The tree at the joint values last noted, stamped `ns`, as an encoded
        `FrameTransforms`: byte for byte what the SDK's `FrameTransforms.encode` gives, in a
        fraction of its time (a fleet's recording makes thousands a second). Each transform's
        fields after its timestamp are kept while its joint stands still."""
        stamp = _message(1, _timestamp_fields(ns))
        size = len(stamp)
        degrees = self._degrees[tree]
        slots = self._slots.get(tree)
        if slots is None:
            slots = self._slots[tree] = self._slots_of(tree)
        parts: list[bytes] = []
        for slot in slots:
            joint, spec = slot.joint, slot.spec
            noted = None if spec is None else degrees.get(spec.name)
            if slot.fields is None or noted != slot.noted:
                value = 0.0 if spec is None or noted is None else spec.to_urdf(noted)
                rotation, translation = IDENTITY if joint is None else joint.transform(value)
                if translation is not slot.translation:  # (a revolute joint's never changes)
                    slot.translation = translation
                    slot.frames_and_translation = slot.frames + _vector(4, translation)
                slot.noted = noted
                slot.fields = slot.frames_and_translation + _vector(5, rotation)
            length = size + len(slot.fields)
            parts += (_HEADS[length] if length < 128 else b"\x0a" + _varint(length), stamp)
            parts.append(slot.fields)
        return b"".join(parts)

    def _slots_of(self, tree: str) -> list[_Slot]:
        """A tree's transforms: the world to its root, then each joint's."""
        by_urdf_name = {spec.urdf_name: spec for spec in self.model.joints}
        root = _Slot(None, None, _text(2, WORLD) + _text(3, self.frame(tree, self.kinematics.root)))
        return [root] + [
            _Slot(
                joint,
                by_urdf_name.get(joint.name),
                _text(2, self.frame(tree, joint.parent)) + _text(3, self.frame(tree, joint.child)),
            )
            for joint in self.kinematics.joints
        ]

    def scene(self, ns: int) -> bytes:
        """The 3D model as an encoded `SceneUpdate`: meshes that follow the real tree's links
        and a skeleton (joint to joint) that follows the virtual one. Made when asked (once
        per file, or per new viewer), not kept: a few MB per robot."""
        stamp = timestamp(ns)
        meshes: dict[str, list[ModelPrimitive]] = {}
        for visual in visuals(self.model.urdf_path):
            media_type, data = _model(visual.path)
            meshes.setdefault(visual.link, []).append(
                ModelPrimitive(
                    pose=_pose(visual.origin),
                    scale=Vector3(x=visual.scale[0], y=visual.scale[1], z=visual.scale[2]),
                    color=_MESH_COLOR,
                    override_color=True,
                    media_type=media_type,
                    data=data,
                )
            )
        bones: dict[str, list[Point3]] = {}
        for joint in self.kinematics.joints:
            x, y, z = joint.origin[1]
            bones.setdefault(joint.parent, []).extend([Point3(), Point3(x=x, y=y, z=z)])
        entities = []
        for link in self.kinematics.links:
            real, virtual = self.frame("real", link), self.frame("virtual", link)
            if link in meshes:
                entities.append(
                    SceneEntity(
                        timestamp=stamp, frame_id=real, id=real, frame_locked=True,
                        models=meshes[link],
                    )
                )  # fmt: skip
            if link in bones:
                line = LinePrimitive(
                    type=LinePrimitiveLineType.LineList,
                    thickness=6.0,
                    scale_invariant=True,
                    points=bones[link],
                    color=_SKELETON_COLOR,
                )
                entities.append(
                    SceneEntity(
                        timestamp=stamp, frame_id=virtual, id=virtual, frame_locked=True,
                        lines=[line],
                    )
                )  # fmt: skip
        return bytes(SceneUpdate(entities=entities).encode())

    def log(self, event: RobotEvent, ns: int) -> bytes | None:
        """The log line of an event worth a place on the timeline, encoded, or None."""
        said = _log_line(event)
        if said is None:
            return None
        level, text = said
        return bytes(
            Log(timestamp=timestamp(ns), level=level, message=text, name=self.robot_id).encode()
        )

    def messages(self, event: RobotEvent, ns: int) -> list[tuple[str, bytes]]:
        """(kind, encoded message) for everything an event shows in Foxglove."""
        pose = pose_of(event)
        if pose is not None:
            return [("tf", self.transforms(*pose, ns))]
        line = self.log(event, ns)
        return [] if line is None else [("log", line)]


def pose_of(event: RobotEvent) -> tuple[str, Mapping[str, float]] | None:
    """The tree a pose event moves (`TREE_OF`) and its joints; None for other events."""
    if isinstance(event, (TargetsSent, JointStatesReceived)):
        return TREE_OF[type(event)], event.joints
    return None


@functools.lru_cache(maxsize=64)
def _model(path: Path) -> tuple[str, bytes]:
    """A mesh file as embedded in a scene, (media type, data), made once for every robot of
    its type: a binary STL as glTF (`glb`: a quarter of the bytes, shown right whatever the
    viewer's mesh up axis), anything else as it is."""
    if path.suffix.lower() == ".stl":
        try:
            return "model/gltf-binary", glb.for_stl(path)
        except ValueError:  # an ASCII STL
            pass
    return "model/stl", path.read_bytes()


def shows(event: RobotEvent) -> bool:
    """Whether an event can show in Foxglove: all but an accepted command, the most frequent
    event of all (callers skip those without asking a twin)."""
    return not (type(event) is CommandHandled and event.result.accepted)


#: A log line: its level and text.
LogLine = tuple[LogLevel, str]


def _state_line(event: StateChanged) -> LogLine:
    if event.mode is Mode.ESTOPPED:
        return LogLevel.Error, f"E-STOP: {event.estop_reason or event.cause}"
    return LogLevel.Info, f"state {event.mode} (owner {event.owner or 'none'}): {event.cause}"


def _fault_line(event: FaultReported) -> LogLine:
    joint = f" on {event.joint}" if event.joint else ""
    if event.cleared:
        return LogLevel.Info, f"fault {event.code} of {event.peer_id}{joint} over: {event.message}"
    level = _LEVEL_OF_SEVERITY.get(str(event.severity), LogLevel.Warning)
    return level, f"fault {event.code} from {event.peer_id}{joint}: {event.message}"


def _command_line(event: CommandHandled) -> LogLine | None:
    if not shows(event):
        return None
    return LogLevel.Warning, f"refused {event.result.code} ({event.source}): {event.result.message}"


def _peer_line(event: PeerChanged) -> LogLine:
    trouble = ("lost", "refused", "disconnected")
    level = LogLevel.Warning if event.change in trouble else LogLevel.Info
    reason = f": {event.reason}" if event.reason else ""
    code = f" {event.code}" if event.code else ""
    return level, f"{event.role} {event.peer_id} ({event.kind}) {event.change}{code}{reason}"


def _episode_line(event: EpisodeChanged) -> LogLine:
    return LogLevel.Info, f"episode {event.index} {event.change}: {event.task}"


def _intervention_line(event: InterventionChanged) -> LogLine:
    return LogLevel.Info, f"intervention by {event.master} {event.change} ({event.paused} waits)"


def _stop_line(event: MotionStopped) -> LogLine:
    return LogLevel.Warning, f"stopped {event.code} ({event.source}): {event.message}"


def _audit_line(event: Audited) -> LogLine:
    detail = f" ({event.detail})" if event.detail else ""
    return LogLevel.Info, f"{event.user}: {event.action}{detail}"


#: How each robot event shows in Foxglove: a pose event moves one tree of its robot's twin
#: (`tf`): targets sent the commanded one, joint states the measured one; every other event
#: is a line of the log (`_LOG_LINES`: its level and text, or None when it has none).
TREE_OF: dict[type[RobotEvent], str] = {TargetsSent: "virtual", JointStatesReceived: "real"}
_LOG_LINES: dict[type[RobotEvent], Callable[[Any], LogLine | None]] = {
    StateChanged: _state_line,
    FaultReported: _fault_line,
    CommandHandled: _command_line,
    PeerChanged: _peer_line,
    EpisodeChanged: _episode_line,
    Audited: _audit_line,
    InterventionChanged: _intervention_line,
    MotionStopped: _stop_line,
    PolicyInferred: lambda _: None,  # many a second: plotted from its topic, not logged
}
if set(TREE_OF) | set(_LOG_LINES) != set(get_args(RobotEvent)):  # (a new event is shown)
    raise TypeError("every robot event needs its Foxglove form: a tree or a log line")


def _log_line(event: RobotEvent) -> LogLine | None:
    line = _LOG_LINES.get(type(event))  # (none for a pose event)
    return None if line is None else line(event)


# FrameTransforms is encoded here rather than by building the SDK's objects, which cost ~14 us
# a tree of seven transforms: ~3 us at rest, ~4 with one joint moving, ~10 with all of them.
# Protobuf's wire format as the SDK writes it: fields in order, message fields always present,
# zero numbers and empty strings left out.


def _varint(value: int) -> bytes:
    value &= (1 << 64) - 1  # a negative int64 is its two's complement, ten bytes
    out = bytearray()
    while value > 0x7F:
        out.append(value & 0x7F | 0x80)
        value >>= 7
    out.append(value)
    return bytes(out)


def _message(field: int, payload: bytes) -> bytes:
    """A length-delimited field (a message or a string) numbered 1-15."""
    return bytes((field << 3 | 2,)) + _varint(len(payload)) + payload


def _text(field: int, text: str) -> bytes:
    return _message(field, text.encode()) if text else b""


_TAGGED_DOUBLE = struct.Struct("<Bd").pack
_DOUBLE_TAGS = (0x09, 0x11, 0x19, 0x21)  # double fields 1-4
_THREE = struct.Struct("<BBBdBdBd").pack
_FOUR = struct.Struct("<BBBdBdBdBd").pack


def _vector(field: int, values: tuple[float, ...]) -> bytes:
    """A `Vector3` or `Quaternion` field: its doubles numbered 1, 2, ... (zeros, either sign,
    left out). One with no zero packs in one call."""
    if 0.0 not in values:
        if len(values) == 3:
            x, y, z = values
            return _THREE(field << 3 | 2, 27, 0x09, x, 0x11, y, 0x19, z)
        if len(values) == 4:
            x, y, z, w = values
            return _FOUR(field << 3 | 2, 36, 0x09, x, 0x11, y, 0x19, z, 0x21, w)
    tags = _DOUBLE_TAGS[: len(values)]
    payload = b"".join([_TAGGED_DOUBLE(tag, v) for tag, v in zip(tags, values, strict=True) if v])
    return _message(field, payload)


def _timestamp_fields(ns: int) -> bytes:
    seconds, nanos = divmod(ns, 1_000_000_000)
    return (b"\x08" + _varint(seconds) if seconds else b"") + (
        b"\x10" + _varint(nanos) if nanos else b""
    )


#: The head of a `FrameTransforms.transforms` element (field 1) of each length below 128.
_HEADS = tuple(bytes((0x0A, n)) for n in range(128))


@dataclass(eq=False)
class _Slot:
    """One transform of a tree as `Twin.encode_tree` keeps it: its joint (None for the world
    to the root) and wire joint (None if not commanded), the encoded frame ids, and the fields
    after the timestamp at the joint value last encoded."""

    joint: UrdfJoint | None
    spec: JointSpec | None
    frames: bytes
    noted: float | None = None
    fields: bytes | None = None
    translation: tuple[float, float, float] | None = None
    frames_and_translation: bytes = b""


def _pose(pose: KinematicPose) -> Pose:
    (qx, qy, qz, qw), (x, y, z) = pose
    return Pose(position=Vector3(x=x, y=y, z=z), orientation=Quaternion(x=qx, y=qy, z=qz, w=qw))


#: One message to write: (robot id, kind, encoded message, log time in ns), as `mcap_file`.
ViewItem = tuple[str, str, bytes, int]


class Twins:
    """The twin of every robot a recording names, made on first use from its robot type.

    `robots` is the recording's robot metadata (id -> {"robot_type": ...}); `models` holds the
    robots' models where the recorder sent them (else the type is loaded by name). A robot
    whose type cannot be loaded is recorded without Foxglove's view (said once on stderr).
    """

    #: `shows`, for the recording process, which holds Twins without importing this module
    #: (the SDK loads only when the view is recorded).
    shows = staticmethod(shows)

    def __init__(
        self,
        robots: Mapping[str, Mapping[str, str]],
        models: Mapping[str, RobotModel] | None = None,
        rate: float = 0.0,
    ) -> None:
        self.robots = robots
        self.models = {} if models is None else models
        self._twins: dict[str, Twin | None] = {}
        #: Transforms of one tree at most `rate` a second (0: one per record); `flush` adds
        #: the newest pose of every tree the rate held back, so a pose at rest is never stale.
        self._spacing = int(1e9 / rate) if rate > 0 else 0
        self._last: dict[tuple[str, str], int] = {}
        self._held: dict[tuple[str, str], int] = {}

    def twin(self, robot_id: str) -> Twin | None:
        """The robot's twin, or None if it has none."""
        if robot_id not in self._twins:
            self._twins[robot_id] = self._make(robot_id)
        return self._twins[robot_id]

    def _make(self, robot_id: str) -> Twin | None:
        model = self.models.get(robot_id)
        robot_type = self.robots.get(robot_id, {}).get("robot_type")
        if model is None and robot_type is None:
            return None
        try:
            return Twin(robot_id, model or load_robot_model(str(robot_type)))
        except (ArenaError, OSError, ValueError, ElementTree.ParseError) as exc:
            print(f"arena: no 3D view of {robot_id!r} in recordings: {exc}", file=sys.stderr)
            return None

    def items(self, robot_id: str, event: RobotEvent, log_time: int) -> list[ViewItem]:
        """What an event shows in Foxglove, as items to write (transforms as the rate
        allows; call `flush` after a batch of events)."""
        twin = self.twin(robot_id)
        if twin is None:
            return []
        pose = pose_of(event)
        if pose is not None:
            tree = pose[0]
            twin.update(*pose)
            key = (robot_id, tree)
            if log_time - self._last.get(key, -(1 << 62)) < self._spacing:
                self._held[key] = log_time
                return []
            self._last[key] = log_time
            self._held.pop(key, None)
            return [(robot_id, "tf", twin.encode_tree(tree, log_time), log_time)]
        line = twin.log(event, log_time)
        return [] if line is None else [(robot_id, "log", line, log_time)]

    def flush(self) -> list[ViewItem]:
        """The transforms the rate held back: each tree's newest pose, at its own time."""
        found = []
        for (robot_id, tree), log_time in self._held.items():
            twin = self._twins.get(robot_id)
            if twin is not None:
                found.append((robot_id, "tf", twin.encode_tree(tree, log_time), log_time))
                self._last[(robot_id, tree)] = log_time
        self._held.clear()
        return found

    def introduce(self, robot_id: str, log_time: int) -> list[ViewItem]:
        """The robot's 3D model, for the first of its records in a file."""
        twin = self.twin(robot_id)
        return [] if twin is None else [(robot_id, "scene", twin.scene(log_time), log_time)]


def layout(robot_ids: list[str], joint_names: tuple[str, ...]) -> str:
    """A Foxglove layout (JSON) for these robots: the 3D panel with every twin, a plot per
    joint of the commanded target against the measured value, and the log."""
    import foxglove.layouts as fl  # only this command needs the layout builder

    scenes = {
        topic_name: fl.BaseRendererSceneUpdateTopicSettings(visible=True)
        for topic_name in (f"/robots/{robot_id}/scene" for robot_id in robot_ids)
    }
    three_d = fl.ThreeDeePanel(
        title="Twins: meshes measured, blue skeleton commanded",
        config=fl.ThreeDeeConfig(
            follow_tf=WORLD,
            topics=scenes,  # type: ignore[arg-type]
            # URDF meshes are Z-up; the glTF Arena embeds shows right with either setting,
            # and this keeps a mesh embedded as it is (an ASCII STL) right too.
            scene=fl.BaseRendererSceneSettings(mesh_up_axis="z_up"),
        ),
    )
    plots = [
        fl.SplitItem(
            content=fl.PlotPanel(
                title=joint,
                config=fl.PlotConfig(
                    paths=[
                        series
                        for robot_id in robot_ids
                        for series in (
                            fl.PlotSeries(
                                value=f"/robots/{robot_id}/targets.joints.{joint}",
                                label=f"{robot_id} commanded",
                            ),
                            fl.PlotSeries(
                                value=f"/robots/{robot_id}/joint_states.joints.{joint}",
                                label=f"{robot_id} measured",
                            ),
                        )
                    ],
                    show_legend=True,
                ),
            )
        )
        for joint in joint_names
    ]
    logs = fl.SplitItem(content=fl.LogPanel(title="E-stops, faults, refusals, peers"))
    content = fl.SplitContainer(
        direction="row",
        items=[
            fl.SplitItem(proportion=2, content=three_d),
            fl.SplitItem(content=fl.SplitContainer(direction="column", items=[*plots, logs])),
        ],
    )
    return str(fl.Layout(content=content).to_json())
