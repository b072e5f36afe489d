"""The fleet's key space on Zenoh (specs/fleet.md). Everything lives under `arena/<fleet>/`.

arena/<fleet>/<node>/alive                      liveliness token of a node
arena/<fleet>/<node>/robots/<id>/alive          liveliness token of each robot a node owns
arena/<fleet>/<node>/robots/<id>/state          publication: the robot's state changes
                                                (e-stops among them), JSON of `StateMessage`
arena/<fleet>/<node>/info                       queryable: name, version, robots (JSON)
arena/<fleet>/<node>/estop                      queryable: e-stop every robot, answer the ack
arena/<fleet>/<node>/http                       queryable: one REST call on a robot of the node
arena/<fleet>/<node>/tunnel                     queryable: open a WebSocket tunnel to a robot
arena/<fleet>/<node>/tunnel/<tid>/in            what the client sends, to the robot's node
arena/<fleet>/<origin>/tunnel/<tid>/out         what the robot's node sends back
"""

from __future__ import annotations

import re

#: Node and fleet names: safe as one Zenoh key chunk, in a file name and in a URL.
NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_-]{0,63}$")


def prefix(fleet: str, node: str = "*") -> str:
    """`arena/<fleet>/<node>` (any node by default)."""
    return f"arena/{fleet}/{node}"


def node_alive(fleet: str, node: str = "*") -> str:
    """A node's liveliness token."""
    return f"{prefix(fleet, node)}/alive"


def robot_alive(fleet: str, node: str = "*", robot: str = "*") -> str:
    """A robot's liveliness token."""
    return f"{prefix(fleet, node)}/robots/{robot}/alive"


def robot_state(fleet: str, node: str = "*", robot: str = "*") -> str:
    """Where a robot's state changes are published."""
    return f"{prefix(fleet, node)}/robots/{robot}/state"


def service(fleet: str, node: str, name: str) -> str:
    """A node's queryable: `info`, `estop`, `http` or `tunnel`."""
    return f"{prefix(fleet, node)}/{name}"


def tunnel(fleet: str, node: str, tunnel_id: str, direction: str) -> str:
    """One direction (`in` to the robot's node, `out` back to the client's) of a tunnel."""
    return f"{prefix(fleet, node)}/tunnel/{tunnel_id}/{direction}"


def parse(key: str) -> list[str]:
    """The chunks after `arena/<fleet>/`: [node, ...]."""
    return key.split("/")[2:]
