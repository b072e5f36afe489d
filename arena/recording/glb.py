"""A mesh as binary glTF (GLB), the form Foxglove's view embeds in a robot's scene.

Binary STL stores every triangle's three corners and a normal: 50 bytes a triangle, and most
corners repeated about six times. A GLB of the same triangles keeps each corner once and the
triangles as indices: the so-arm100's meshes shrink from 3.0 to 0.7 MB, and a scene costs a
fifth of the time to compress (it is written once per robot and file, so a fleet's first
second of recording was mostly its meshes). Normals are left out: glTF viewers then shade each
face flat, as an STL's facet normals would.

URDF meshes are Z-up; glTF is Y-up by definition, and Foxglove turns glTF models from Y-up to
Z-up (a quarter turn about X) whatever its "mesh up axis" setting, which applies only to
formats without an up axis such as STL. So the corners are stored turned the other way, and the
model shows as the URDF means it with any setting.
"""

from __future__ import annotations

import json
import struct
from typing import Any

_MAGIC = 0x46546C67  # "glTF"
_JSON_CHUNK = 0x4E4F534A  # "JSON"
_BIN_CHUNK = 0x004E4942  # "BIN\0"
_FLOAT, _UNSIGNED_SHORT, _UNSIGNED_INT = 5126, 5123, 5125
_ARRAY_BUFFER, _ELEMENT_ARRAY_BUFFER = 34962, 34963


def from_triangles(corners: Any) -> bytes:
    """A GLB of a triangle soup: `corners` is an (3n, 3) array of Z-up points (each row a
    corner, three rows a triangle, counter-clockwise seen from outside, as STL has them)."""
    import numpy as np

    points = np.ascontiguousarray(np.asarray(corners, dtype="<f4").reshape(-1, 3))
    if len(points) == 0 or len(points) % 3:
        raise ValueError("a mesh needs whole triangles")
    # Each distinct corner once (exact float equality, as an STL repeats them), in first-seen
    # order is not needed: glTF indexes whatever order the vertices come in.
    keys = points.view(np.dtype((np.void, 12))).ravel()
    _, first, index = np.unique(keys, return_index=True, return_inverse=True)
    vertices = points[first]
    # Z-up to Y-up: (x, y, z) -> (x, z, -y), undone by the viewer's quarter turn about X.
    y_up = np.column_stack((vertices[:, 0], vertices[:, 2], -vertices[:, 1])).astype("<f4")
    short = len(y_up) <= 0xFFFF
    indices = index.reshape(-1).astype("<u2" if short else "<u4")
    positions_bytes = y_up.tobytes()
    indices_bytes = indices.tobytes()
    indices_bytes += b"\0" * (-len(indices_bytes) % 4)
    document = {
        "asset": {"version": "2.0", "generator": "arena"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1}]}],
        "buffers": [{"byteLength": len(positions_bytes) + len(indices_bytes)}],
        "bufferViews": [
            {
                "buffer": 0,
                "byteOffset": 0,
                "byteLength": len(positions_bytes),
                "target": _ARRAY_BUFFER,
            },
            {
                "buffer": 0,
                "byteOffset": len(positions_bytes),
                "byteLength": len(indices) * indices.itemsize,
                "target": _ELEMENT_ARRAY_BUFFER,
            },
        ],
        "accessors": [
            {
                "bufferView": 0,
                "componentType": _FLOAT,
                "count": len(y_up),
                "type": "VEC3",
                "min": [float(v) for v in y_up.min(axis=0)],
                "max": [float(v) for v in y_up.max(axis=0)],
            },
            {
                "bufferView": 1,
                "componentType": _UNSIGNED_SHORT if short else _UNSIGNED_INT,
                "count": len(indices),
                "type": "SCALAR",
            },
        ],
    }
    text = json.dumps(document, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 4)
    binary = positions_bytes + indices_bytes
    length = 12 + 8 + len(text) + 8 + len(binary)
    return b"".join(
        (
            struct.pack("<III", _MAGIC, 2, length),
            struct.pack("<II", len(text), _JSON_CHUNK),
            text,
            struct.pack("<II", len(binary), _BIN_CHUNK),
            binary,
        )
    )
