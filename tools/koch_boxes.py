"""Write the Koch's link meshes (arena/robot_types/koch/meshes/*.stl, and their .glb) from the
Koch v1.1's CAD: each link is the bounding box of its printed part and the bounding box of its
servo, measured in the link's frame on the follower's SolidWorks export (the Koch v1.1
repository's `simulation/follower.urdf` meshes, Apache-2.0; its joint origins are the ones
`koch.urdf` uses). The CAD meshes themselves are not shipped: their boxes are enough for the
twin's shape and the collision guard's capsules, which are fitted to every vertex.

    python tools/koch_boxes.py        # rewrites the meshes; tests/test_koch_model.py checks them
"""

from __future__ import annotations

import struct
import sys
from pathlib import Path

Box = tuple[tuple[float, float, float], tuple[float, float, float]]

#: Per Arena link (its mesh file): the CAD part's and its servo's bounds (metres, link frame),
#: as measured on the follower's meshes (`link_N.STL` and `link_N_motor.STL`).
LINKS: dict[str, tuple[Box, ...]] = {
    "base": (  # base_link: the printed base plate and the pan servo (XL430-W250) standing on it
        ((0.0, -0.0675, 0.0), (0.08, 0.091, 0.009)),
        ((0.0007, -0.0143, 0.003), (0.0472, 0.0143, 0.0409)),
    ),
    "shoulder": (  # link_1: the shoulder bracket and the lift servo (XL430-W250)
        ((-0.0143, -0.02, -0.0019), (0.0383, 0.02, 0.009)),
        ((-0.0113, -0.0209, 0.0011), (0.0353, 0.02, 0.0297)),
    ),
    "upper_arm": (  # link_2: shoulder to elbow, and the elbow servo (XL330-M288)
        ((-0.013, -0.0011, -0.0129), (0.013, 0.0429, 0.119)),
        ((-0.0243, 0.0065, 0.0983), (0.0097, 0.0354, 0.1183)),
    ),
    "forearm": (  # link_3: elbow to wrist extension, and the wrist-flex servo (XL330-M288)
        ((-0.0817, -0.0031, -0.0085), (0.0084, 0.032, 0.0145)),
        ((-0.11, 0.0, -0.0073), (-0.076, 0.029, 0.0127)),
    ),
    "wrist": (  # link_4: elbow to wrist, and the wrist-roll servo (XL330-M288)
        ((-0.019, -0.0033, -0.011), (0.009, 0.0387, 0.011)),
        ((-0.045, 0.0036, -0.01), (-0.019, 0.0376, 0.01)),
    ),
    "hand": (  # link_5: the gripper's static part (fixed jaw) and the gripper servo (XL330-M288)
        ((-0.0689, -0.0175, -0.0148), (0.0, 0.0202, 0.0148)),
        ((-0.0232, -0.017, -0.0144), (-0.0031, 0.017, 0.0145)),
    ),
    "jaw": (  # link_6: the gripper's moving part
        ((-0.0557, -0.0079, -0.0322), (0.0083, 0.0131, 0.0033)),
    ),
}

#: A box's faces as corner indices (bit 0: x high, bit 1: y high, bit 2: z high), outward.
_FACES = (
    (0, 2, 3, 1),  # z low
    (4, 5, 7, 6),  # z high
    (0, 1, 5, 4),  # y low
    (2, 6, 7, 3),  # y high
    (0, 4, 6, 2),  # x low
    (1, 3, 7, 5),  # x high
)


def box_triangles(box: Box) -> list[tuple[tuple[float, float, float], ...]]:
    """A box's twelve triangles, wound counter-clockwise seen from outside."""
    low, high = box
    corners = [
        (
            high[0] if k & 1 else low[0],
            high[1] if k & 2 else low[1],
            high[2] if k & 4 else low[2],
        )
        for k in range(8)
    ]
    triangles = []
    for a, b, c, d in _FACES:
        triangles.append((corners[a], corners[b], corners[c]))
        triangles.append((corners[a], corners[c], corners[d]))
    return triangles


def stl(boxes: tuple[Box, ...]) -> bytes:
    """A binary STL holding `boxes` (normals left zero: readers compute them)."""
    triangles = [t for box in boxes for t in box_triangles(box)]
    out = [b"Arena: Koch v1.1 link boxes from its CAD".ljust(80, b" ")]
    out.append(struct.pack("<I", len(triangles)))
    for triangle in triangles:
        out.append(struct.pack("<3f", 0.0, 0.0, 0.0))
        for corner in triangle:
            out.append(struct.pack("<3f", *corner))
        out.append(struct.pack("<H", 0))
    return b"".join(out)


def main() -> int:
    """Write every link's STL and GLB beside koch.urdf."""
    from arena.recording import glb

    folder = Path(__file__).resolve().parent.parent / "arena" / "robot_types" / "koch" / "meshes"
    paths = []
    for name, boxes in LINKS.items():
        path = folder / f"{name}.stl"
        path.write_bytes(stl(boxes))
        paths.append(str(path))
    return glb.main(paths)


if __name__ == "__main__":
    sys.exit(main())
