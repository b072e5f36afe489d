"""rmw_zenoh's wire format as of ROS 2 Jazzy, and the rule that turns robot ids into ROS names.

Pure functions, no Zenoh: key expressions of topics and services, liveliness tokens, the
attachment every sample and service call carries, entity GIDs. The format is rmw_zenoh's
docs/design.md ("Topic and Service name mapping", "Graph Cache", "Publishers"); specs/ros2.md
lists it with examples.
"""

from __future__ import annotations

import re
import struct
from collections.abc import Iterable
from dataclasses import dataclass

#: The hermetic prefix of every liveliness token.
ADMIN_SPACE = "@ros2_lv"
#: Entity kinds in a token.
NODE, PUBLISHER, SUBSCRIPTION, SERVICE = "NN", "MP", "MS", "SS"
#: QoS in a token (rmw_zenoh's `qos_to_keyexpr`, fields left empty where they are the
#: default: reliable, volatile, keep last; the depth is always written).
QOS_DEPTH_10 = "::,10:,:,:,,"
QOS_DEPTH_100 = "::,100:,:,:,,"  # /tf, as tf2's broadcaster
QOS_TRANSIENT_LOCAL = ":1:,1:,:,:,,"  # robot_description, as robot_state_publisher
#: The attachment: sequence number, source timestamp (ns), GID length, GID.
ATTACHMENT = struct.Struct("<qqB16s")
GID_SIZE = 16

_NOT_NAME = re.compile(r"[^A-Za-z0-9_]+")
_UNDERSCORES = re.compile(r"__+")


def dds_type(ros_type: str) -> str:
    """The type's DDS name as rmw_zenoh writes it: `std_msgs/msg/String` ->
    `std_msgs::msg::dds_::String_`."""
    package, kind, name = ros_type.split("/")
    return f"{package}::{kind}::dds_::{name}_"


def mangle(name: str) -> str:
    """A name as one chunk of a token: each `/` becomes `%` (`/` itself is `%`)."""
    return name.replace("/", "%")


def data_key(domain: int, name: str, ros_type: str, type_hash: str) -> str:
    """The key expression of a topic or a service: `<domain>/<name>/<type>/<hash>`, the fully
    qualified name without its leading slash."""
    return f"{domain}/{name.strip('/')}/{dds_type(ros_type)}/{type_hash}"


@dataclass(frozen=True, slots=True)
class Entity:
    """One entity of the ROS graph as its liveliness token describes it."""

    domain: int
    session: str  # the Zenoh session id (hex)
    node_id: int
    entity_id: int
    kind: str  # NODE, PUBLISHER, SUBSCRIPTION or SERVICE
    node: str  # the node's name
    namespace: str = "/"
    topic: str = ""  # fully qualified topic or service name (not for a node)
    ros_type: str = ""
    type_hash: str = ""
    qos: str = QOS_DEPTH_10

    def token(self) -> str:
        """The liveliness token's key expression."""
        parts = [
            ADMIN_SPACE,
            str(self.domain),
            self.session,
            str(self.node_id),
            str(self.entity_id),
            self.kind,
            "%",  # no SROS enclave
            mangle(self.namespace),
            self.node,
        ]
        if self.kind != NODE:
            parts += [mangle(self.topic), dds_type(self.ros_type), self.type_hash, self.qos]
        return "/".join(parts)

    def gid(self) -> bytes:
        """The entity's GID: XXH3-128 of its token, low 64 bits then high, little-endian
        (rmw_zenoh's `Entity` constructor)."""
        return entity_gid(self.token())


def entity_gid(token: str) -> bytes:
    """The GID of the entity whose liveliness token is `token`."""
    import xxhash  # the `ros2` extra's: imported where used, so settings check without it

    return xxhash.xxh3_128_intdigest(token.encode()).to_bytes(GID_SIZE, "little")


def token_topic(token: str) -> tuple[str, str] | None:
    """(kind, fully qualified topic) of a publisher's or subscription's token; None for
    anything else."""
    parts = token.split("/")
    if len(parts) != 13 or parts[0] != ADMIN_SPACE or parts[5] not in (PUBLISHER, SUBSCRIPTION):
        return None
    return parts[5], parts[9].replace("%", "/")


def attachment(sequence: int, timestamp_ns: int, gid: bytes) -> bytes:
    """The attachment of a sample, a request or a reply."""
    return ATTACHMENT.pack(sequence, timestamp_ns, GID_SIZE, gid)


def read_attachment(data: bytes) -> tuple[int, int, bytes]:
    """(sequence, timestamp ns, GID) of an attachment; ValueError when it is not one."""
    if len(data) != ATTACHMENT.size:
        raise ValueError(f"an attachment is {ATTACHMENT.size} bytes, not {len(data)}")
    sequence, timestamp, size, gid = ATTACHMENT.unpack(data)
    if size != GID_SIZE:
        raise ValueError(f"a GID is {GID_SIZE} bytes, not {size}")
    return sequence, timestamp, gid


def ros_name(robot_id: str) -> str:
    """A robot id as a ROS name token: every run of characters other than ASCII letters,
    digits and `_` becomes one `_`, runs of `_` become one, a leading digit gets `r_` before
    it (`demo-arm` -> `demo_arm`, `3.arm` -> `r_3_arm`)."""
    name = _UNDERSCORES.sub("_", _NOT_NAME.sub("_", robot_id))
    if not name or name == "_":
        return "robot"
    return f"r_{name}" if name[0].isdigit() else name


class NameBook:
    """The ROS names in use: a robot whose name is taken already gets `_2`, `_3`, ... after it
    (the robot that came first keeps the plain name while it lives)."""

    def __init__(self) -> None:
        self._names: dict[str, str] = {}  # robot id -> ROS name

    def take(self, robot_id: str, taken: Iterable[str] = ()) -> str:
        """The ROS name of a robot now joining."""
        used = set(self._names.values()) | set(taken)
        base = name = ros_name(robot_id)
        count = 1
        while name in used:
            count += 1
            name = f"{base}_{count}"
        self._names[robot_id] = name
        return name

    def release(self, robot_id: str) -> None:
        """The robot is gone: its name is free."""
        self._names.pop(robot_id, None)
