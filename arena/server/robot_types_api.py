"""REST for robot types: their joints, URDF and meshes (what a 3D twin needs to draw a robot)."""

from __future__ import annotations

from typing import Any

import trio
from quart import Blueprint, Response

from arena.protocol.errors import ArenaError, ErrorCode
from arena.robot.model import RobotModel, list_robot_types, load_robot_model
from arena.server.files import send_folder_file

blueprint = Blueprint("robot_types", __name__)

# Only these files of a type's folder are served: its meshes, never robot.toml or anything else.
MESH_SUFFIXES = (".stl", ".dae", ".obj")


def describe_type(model: RobotModel) -> dict[str, Any]:
    """A robot type as the API shows it: joints with wire limits and their URDF `neutral`."""
    base = f"/api/robot-types/{model.robot_type}"
    return {
        "id": model.robot_type,
        "description": model.description,
        "urdf": f"{base}/urdf",
        "files": f"{base}/files/",
        "joints": [
            {
                "name": joint.name,
                "servo_id": joint.servo_id,
                "aliases": list(joint.aliases),
                "lower": round(joint.lower, 6),
                "upper": round(joint.upper, 6),
                "velocity": round(joint.max_velocity, 6),
                # a wire value d stands for URDF radians neutral + d * radians_per_unit
                "neutral": round(joint.neutral, 9),
                "unit": joint.unit,
                "radians_per_unit": round(joint.radians_per_unit, 12),
            }
            for joint in model.joints
        ],
    }


@blueprint.get("/api/robot-types")
async def list_types() -> list[dict[str, Any]]:
    """Every robot type Arena can create."""
    return [describe_type(load_robot_model(name)) for name in list_robot_types()]


@blueprint.get("/api/robot-types/<robot_type>")
async def get_type(robot_type: str) -> dict[str, Any]:
    """One robot type."""
    return describe_type(load_robot_model(robot_type))


@blueprint.get("/api/robot-types/<robot_type>/urdf")
async def get_urdf(robot_type: str) -> Response:
    """The type's URDF; mesh file names in it are relative to `/api/robot-types/{type}/files/`."""
    model = load_robot_model(robot_type)
    urdf = await trio.Path(model.urdf_path).read_bytes()
    return Response(urdf, content_type="application/xml")


@blueprint.get("/api/robot-types/<robot_type>/files/<path:name>")
async def get_file(robot_type: str, name: str) -> Response:
    """A mesh of the type's folder (STL, COLLADA or OBJ); no other file is served."""
    folder = load_robot_model(robot_type).urdf_path.parent
    if not name.lower().endswith(MESH_SUFFIXES):
        raise ArenaError(ErrorCode.NOT_FOUND, f"Only meshes are served here, not {name!r}.")
    missing = f"Robot type {robot_type!r} has no {name!r}."
    response = await send_folder_file(folder, name, missing)
    response.cache_control.max_age = 3600
    return response
