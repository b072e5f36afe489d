"""Cutting a byte stream into servo packets, for either family's simulated bus.

Both protocols frame a packet the same way: a fixed header, the servo id and a length field at
fixed places, then that many bytes ending in a check. Finding the header, sliding past a false
one, and waiting for the rest of a frame are the same for both; `FrameParser` does that, and a
family's parser says where its id and length are and how a whole frame is checked and read.
"""

from __future__ import annotations

from typing import ClassVar, Generic, TypeVar

F = TypeVar("F")


class FrameParser(Generic[F]):
    """Incremental parser: `feed(data)` returns the frames completed, as the family decodes
    them (its packets, and the frames whose check failed)."""

    HEADER: ClassVar[bytes]
    HEAD_SIZE: ClassVar[int]  # the header, the id and the length field

    def __init__(self) -> None:
        self._buffer = bytearray()

    def _frame_size(self, head: bytes) -> int | None:
        """The whole frame's size from its first `HEAD_SIZE` bytes; None: no real header."""
        raise NotImplementedError

    def _decode(self, frame: bytes) -> F:
        """One whole frame: a packet, or a corrupt frame when its check fails."""
        raise NotImplementedError

    def feed(self, data: bytes) -> list[F]:
        """Add received bytes; return every frame they complete, in order."""
        self._buffer += data
        found: list[F] = []
        buffer = self._buffer
        while True:
            start = buffer.find(self.HEADER)
            if start < 0:
                # Keep a tail that may be the start of the next header.
                keep = next(
                    (
                        n
                        for n in range(len(self.HEADER) - 1, 0, -1)
                        if buffer.endswith(self.HEADER[:n])
                    ),
                    0,
                )
                del buffer[: len(buffer) - keep]
                return found
            del buffer[:start]
            if len(buffer) < self.HEAD_SIZE:
                return found
            end = self._frame_size(bytes(buffer[: self.HEAD_SIZE]))
            if end is None:
                del buffer[:1]  # not a real header: slide by one
                continue
            if len(buffer) < end:
                return found
            frame = bytes(buffer[:end])
            del buffer[:end]
            found.append(self._decode(frame))

    def clear(self) -> None:
        """Drop any partial frame."""
        self._buffer.clear()
