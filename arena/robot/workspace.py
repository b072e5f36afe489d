"""Where the arm may go: the floor, the keep-out boxes and the margin the collision guard keeps,
and their JSON form (`robot.toml`'s `[workspace]` table and the REST body are the same shape).

The collision model (`collision.py`) takes a `Workspace` as plain values; only the robot type's
loader (`model.py`) and the REST layer read or write the JSON form, through `workspace_from_json`
and `workspace_to_json`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

from arena.robot.kinematics import Vector

#: What a move that would collide does: refused, or stopped short at the last safe pose
#: checked on its way (reported as clamped).
POLICIES = ("refuse", "stop-short")
#: Keep-out boxes a workspace may hold (each costs every check a little).
MAX_BOXES = 16


@dataclass(frozen=True, slots=True)
class Box:
    """A keep-out box, axis-aligned in the root link's frame (metres)."""

    name: str
    low: Vector
    high: Vector


@dataclass(frozen=True, slots=True)
class Workspace:
    """Where the arm may be: above `floor` (z in the root frame; None: no floor), outside the
    keep-out boxes, with `margin` metres kept free around every link."""

    floor: float | None = None
    keep_out: tuple[Box, ...] = ()
    margin: float = 0.005
    policy: str = "refuse"


def workspace_to_json(workspace: Workspace) -> dict[str, object]:
    """The workspace as the REST API shows it."""
    return {
        "floor": workspace.floor,
        "margin": workspace.margin,
        "policy": workspace.policy,
        "keep_out": [
            {"name": b.name, "min": list(b.low), "max": list(b.high)} for b in workspace.keep_out
        ],
    }


def workspace_from_json(data: Mapping[str, object]) -> Workspace:
    """A workspace from `robot.toml`'s `[workspace]` or a REST body; ValueError says what is
    wrong."""
    unknown = set(data) - {"floor", "margin", "policy", "keep_out"}
    if unknown:
        raise ValueError(f"unknown workspace keys: {', '.join(sorted(unknown))}")
    floor = data.get("floor")
    margin = data.get("margin", 0.005)
    policy = data.get("policy", "refuse")
    if floor is not None and not _finite(floor):
        raise ValueError("floor must be a number of metres (or absent: no floor)")
    if not _finite(margin) or not 0 <= float(margin) <= 0.5:  # type: ignore[arg-type]
        raise ValueError("margin must be from 0 to 0.5 metres")
    if policy not in POLICIES:
        raise ValueError(f"policy must be one of {', '.join(POLICIES)}")
    boxes = data.get("keep_out", [])
    if not isinstance(boxes, list) or len(boxes) > MAX_BOXES:
        raise ValueError(f"keep_out must be a list of at most {MAX_BOXES} boxes")
    return Workspace(
        floor=None if floor is None else float(floor),  # type: ignore[arg-type]
        keep_out=tuple(_box(number, entry) for number, entry in enumerate(boxes)),
        margin=float(margin),  # type: ignore[arg-type]
        policy=str(policy),
    )


def _finite(value: object) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


def _box(number: int, entry: object) -> Box:
    if not isinstance(entry, dict):
        raise ValueError(f"keep_out[{number}] must be a table with min and max")
    name = entry.get("name", f"box {number + 1}")
    corners = []
    for key in ("min", "max"):
        corner = entry.get(key)
        if not (isinstance(corner, list) and len(corner) == 3 and all(map(_finite, corner))):
            raise ValueError(f"keep_out[{number}].{key} must be three numbers (metres)")
        corners.append((float(corner[0]), float(corner[1]), float(corner[2])))
    low, high = corners
    if not all(lo < hi for lo, hi in zip(low, high, strict=True)):
        raise ValueError(f"keep_out[{number}]: min must be below max on every axis")
    if not isinstance(name, str) or not 0 < len(name) <= 64:
        raise ValueError(f"keep_out[{number}].name must be a short string")
    return Box(name, low, high)


def point_inside(workspace: Workspace, point: Vector) -> tuple[str, str] | None:
    """What `point` (a goal for the hand, root frame) lies in: ("floor", where) below the
    floor, (a box's name, where) inside a keep-out box; None: in neither. `where` says it in
    words ("50.0 mm below the floor ..."). The margin is left out: a point on the table's
    surface out of reach is out of reach first (one in reach is the guard's to refuse)."""
    if workspace.floor is not None and point[2] < workspace.floor:
        depth = workspace.floor - point[2]
        return "floor", f"{depth * 1000:.1f} mm below the floor (z = {workspace.floor:g} m)"
    for box in workspace.keep_out:
        if all(lo < value < hi for lo, value, hi in zip(box.low, point, box.high, strict=True)):
            return box.name, f"inside keep-out box {box.name!r}"
    return None
