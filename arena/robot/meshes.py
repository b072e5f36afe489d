"""A URDF's visual meshes: where each sits on its link, and its vertices (binary STL).

Used by the collision guard (capsules fitted to the vertices) and by Foxglove's view of a robot
(the meshes embedded in its scene).
"""

from __future__ import annotations

import xml.etree.ElementTree as ElementTree
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from arena.robot.kinematics import Pose, from_rpy, parse_triple, rotate


@dataclass(frozen=True, slots=True)
class Visual:
    """One mesh of a link: where it sits on the link, its file and scale."""

    link: str
    origin: Pose
    path: Path
    scale: tuple[float, float, float]


def visuals(urdf_path: Path) -> list[Visual]:
    """The mesh visuals of a URDF's links; meshes are found beside the URDF (`package://`
    prefixes are dropped), and a mesh that is missing is left out."""
    found: list[Visual] = []
    root = ElementTree.parse(urdf_path).getroot()
    for link in root.iter("link"):
        for visual in link.iter("visual"):
            mesh = visual.find("geometry/mesh")
            if mesh is None or not mesh.get("filename"):
                continue
            name = str(mesh.get("filename"))
            if name.startswith("package://"):
                name = name.removeprefix("package://").split("/", 1)[-1]
            path = (urdf_path.parent / name).resolve()
            if not path.is_file():
                continue
            origin = visual.find("origin")
            xyz = parse_triple(None if origin is None else origin.get("xyz"), (0.0, 0.0, 0.0))
            rpy = parse_triple(None if origin is None else origin.get("rpy"), (0.0, 0.0, 0.0))
            found.append(
                Visual(
                    link=link.get("name", ""),
                    origin=(from_rpy(*rpy), xyz),
                    path=path,
                    scale=parse_triple(mesh.get("scale"), (1.0, 1.0, 1.0)),
                )
            )
    return found


def stl_vertices(path: Path) -> Any:
    """The vertices of a binary STL file as an (n, 3) numpy array of metres (as stored)."""
    import numpy as np

    data = path.read_bytes()
    count = int(np.frombuffer(data, "<u4", 1, 80)[0])
    record = np.dtype([("normal", "<f4", 3), ("vertices", "<f4", (3, 3)), ("attribute", "<u2")])
    if len(data) < 84 + record.itemsize * count:
        raise ValueError(f"{path.name} is not a binary STL file")
    return np.frombuffer(data, record, count, 84)["vertices"].reshape(-1, 3).astype(float)


def link_vertices(urdf_path: Path) -> dict[str, Any]:
    """Every link's mesh vertices in the link's frame (visual origin and scale applied)."""
    import numpy as np

    found: dict[str, list[Any]] = {}
    for visual in visuals(urdf_path):
        if visual.path.suffix.lower() != ".stl":
            continue
        points = stl_vertices(visual.path) * np.asarray(visual.scale)
        rotation, translation = visual.origin
        matrix = np.array([rotate(rotation, axis) for axis in ((1, 0, 0), (0, 1, 0), (0, 0, 1))]).T
        found.setdefault(visual.link, []).append(points @ matrix.T + np.asarray(translation))
    return {link: np.vstack(parts) for link, parts in found.items()}
