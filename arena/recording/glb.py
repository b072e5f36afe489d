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

Converting takes numpy and ~30 ms for the so-arm100, which a short-lived server (each round of
`arena bench versus` is one) paid in its first recorded second. So a robot type ships its
meshes converted beside the STL files (`python -m arena.recording.glb FILE.stl ...` writes
them), each naming the SHA-256 of the STL it was made from; `for_stl` uses such a file only
while that still matches, and converts otherwise.
"""

from __future__ import annotations

import hashlib
import json
import struct
import sys
from pathlib import Path
from typing import Any

_MAGIC = 0x46546C67  # "glTF"
_JSON_CHUNK = 0x4E4F534A  # "JSON"
_BIN_CHUNK = 0x004E4942  # "BIN\0"
_FLOAT, _UNSIGNED_SHORT, _UNSIGNED_INT = 5126, 5123, 5125
_ARRAY_BUFFER, _ELEMENT_ARRAY_BUFFER = 34962, 34963


def for_stl(path: Path) -> bytes:
    """A binary STL file as GLB: the converted file beside it if it was made from these very
    bytes, else converted now (`ValueError` if the file is not a binary STL)."""
    from arena.robot.meshes import stl_vertices

    source = hashlib.sha256(path.read_bytes()).hexdigest()
    built = path.with_suffix(".glb")
    if built.is_file():
        data = built.read_bytes()
        if source_of(data) == source:
            return data
    return from_triangles(stl_vertices(path), source)


def source_of(data: bytes) -> str | None:
    """The SHA-256 of the STL a GLB was made from, as `from_triangles` records it."""
    if len(data) < 20 or struct.unpack_from("<I", data)[0] != _MAGIC:
        return None
    length, kind = struct.unpack_from("<II", data, 12)
    if kind != _JSON_CHUNK:
        return None
    try:
        document = json.loads(data[20 : 20 + length])
        source = document["asset"]["extras"]["source"]
    except (ValueError, KeyError, TypeError):
        return None
    return source if isinstance(source, str) else None


def from_triangles(corners: Any, source: str | None = None) -> bytes:
    """A GLB of a triangle soup: `corners` is an (3n, 3) array of Z-up points (each row a
    corner, three rows a triangle, counter-clockwise seen from outside, as STL has them);
    `source` (the STL's SHA-256) is kept in the asset's extras."""
    import numpy as np

    points = np.ascontiguousarray(np.asarray(corners, dtype="<f4").reshape(-1, 3))
    if len(points) == 0 or len(points) % 3:
        raise ValueError("a mesh needs whole triangles")
    # Each distinct corner once (exact float equality, as an STL repeats them), in sorted
    # byte order: glTF indexes vertices in any order, and this one is the same on every run.
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
        "asset": {"version": "2.0", "generator": "arena", "extras": {"source": source}},
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


def main(argv: list[str]) -> int:
    """Write each binary STL named as GLB beside it (robot types ship them so)."""
    for name in argv:
        path = Path(name)
        path.with_suffix(".glb").write_bytes(for_stl(path))
        print(path.with_suffix(".glb"))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
