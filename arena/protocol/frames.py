"""Frames on the pipes between the server and its helper processes (`arena.child`): a 4-byte
big-endian length, then the body. No I/O, nothing but the standard library: a policy's worker
reads them under whatever interpreter its user runs.
"""

from __future__ import annotations

import struct

HEADER = struct.Struct(">I")


class FrameError(Exception):
    """A frame longer than its pipe's limit, or a body that is not a message it carries."""


def pack(body: bytes, limit: int) -> bytes:
    """`body` as one frame: its length, then itself; `FrameError` past `limit` bytes."""
    if len(body) > limit:
        raise FrameError(f"a message of {len(body)} bytes is over the limit of {limit}")
    return HEADER.pack(len(body)) + body


def frame_length(header: bytes, limit: int) -> int:
    """The body length a frame's 4-byte header announces; `FrameError` past `limit`."""
    (length,) = HEADER.unpack(header)
    if length > limit:
        raise FrameError(f"a frame of {length} bytes is over the limit of {limit}")
    return int(length)
