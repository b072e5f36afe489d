"""The WebSocket wire format (RFC 6455) for the server side: the handshake and frames. No I/O.

Arena speaks WebSocket itself on its hot endpoints (see `ws_transport`): a message is one
frame parse, one unmask and one decode, and the frames of a burst leave in one socket write.
Only what a server needs is here: client frames must be masked, server frames never are, and
no extension is negotiated (so the reserved bits must be clear).
"""

from __future__ import annotations

import base64
import hashlib
import struct
from dataclasses import dataclass, field

OP_CONTINUATION, OP_TEXT, OP_BINARY = 0x0, 0x1, 0x2
OP_CLOSE, OP_PING, OP_PONG = 0x8, 0x9, 0xA
_DATA_OPCODES = (OP_CONTINUATION, OP_TEXT, OP_BINARY)
_CONTROL_OPCODES = (OP_CLOSE, OP_PING, OP_PONG)
_WHOLE_TEXT = 0x80 | OP_TEXT  # the first byte of an unfragmented text frame

#: Close codes the transport itself uses (RFC 6455 7.4.1).
CLOSE_PROTOCOL_ERROR, CLOSE_INVALID_DATA, CLOSE_TOO_BIG = 1002, 1007, 1009
#: Codes a peer may not put in a close frame (reserved, or meaning "no frame").
_UNSENDABLE_CODES = frozenset({1004, 1005, 1006, 1015})

_ACCEPT_GUID = b"258EAFA5-E914-47DA-95CA-C5AB0DC85B11"


def accept_key(client_key: str) -> str:
    """The `Sec-WebSocket-Accept` value for a client's `Sec-WebSocket-Key`."""
    digest = hashlib.sha1(client_key.encode("ascii") + _ACCEPT_GUID).digest()
    return base64.b64encode(digest).decode("ascii")


def valid_client_key(client_key: str) -> bool:
    """A key is 16 random bytes in base64 (RFC 6455 4.1)."""
    try:
        return len(base64.b64decode(client_key, validate=True)) == 16
    except ValueError:
        return False


class ProtocolViolation(Exception):
    """The peer broke the protocol: the connection fails with `code`."""

    def __init__(self, code: int, reason: str) -> None:
        super().__init__(reason)
        self.code = code
        self.reason = reason


@dataclass
class UpgradeRequest:
    """What the client asked for in its opening handshake."""

    path: str
    #: Query parameters (the first value of each).
    args: dict[str, str] = field(default_factory=dict)
    #: Headers, names in lower case.
    headers: dict[str, str] = field(default_factory=dict)
    #: `https` when the connection is TLS (the page's origin would then be https too).
    scheme: str = "http"


class WebSocketClosed(Exception):
    """The connection is closed (by either side); `code` is the peer's close code if any."""

    def __init__(self, code: int, reason: str = "") -> None:
        super().__init__(f"closed with {code} {reason}".strip())
        self.code = code
        self.reason = reason


@dataclass(slots=True)
class Message:
    """A whole data message (text or binary, fragments joined) or one control frame."""

    opcode: int
    payload: bytes


def encode_frame(
    opcode: int, payload: bytes, *, mask: bytes | None = None, fin: bool = True
) -> bytes:
    """One frame: unmasked as a server sends it, or with a 4-byte `mask` as a client must."""
    size = len(payload)
    first = (0x80 if fin else 0) | opcode
    mask_bit = 0x80 if mask is not None else 0
    if size < 126:
        header = struct.pack("!BB", first, mask_bit | size)
    elif size < 65536:
        header = struct.pack("!BBH", first, mask_bit | 126, size)
    else:
        header = struct.pack("!BBQ", first, mask_bit | 127, size)
    if mask is None:
        return header + payload
    return header + mask + _unmask(payload, mask)  # masking and unmasking are the same XOR


def split_unmasked(buffer: bytes | bytearray) -> tuple[int, bytes, int] | None:
    """The first server frame in `buffer`: (opcode, payload, bytes used), None if incomplete.

    For clients (the benchmark's and the tests'); a server parses with `FrameParser`.
    """
    if len(buffer) < 2:
        return None
    size, start = buffer[1] & 0x7F, 2
    if size == 126:
        if len(buffer) < 4:
            return None
        size, start = struct.unpack_from("!H", buffer, 2)[0], 4
    elif size == 127:
        if len(buffer) < 10:
            return None
        size, start = struct.unpack_from("!Q", buffer, 2)[0], 10
    if len(buffer) < start + size:
        return None
    return buffer[0] & 0x0F, bytes(buffer[start : start + size]), start + size


def encode_close(code: int, reason: str = "") -> bytes:
    """A close frame; the reason is cut to fit the 125-byte control-frame limit."""
    text = reason.encode("utf-8")[:123].decode("utf-8", "ignore").encode("utf-8")
    return encode_frame(OP_CLOSE, struct.pack("!H", code) + text)


def parse_close(payload: bytes) -> tuple[int, str]:
    """The code and reason of a peer's close frame (1005 when it gave none)."""
    if not payload:
        return 1005, ""
    if len(payload) == 1:
        raise ProtocolViolation(CLOSE_PROTOCOL_ERROR, "A close frame cannot be one byte long.")
    code = struct.unpack("!H", payload[:2])[0]
    if code < 1000 or code in _UNSENDABLE_CODES or 1016 <= code < 3000 or code >= 5000:
        raise ProtocolViolation(CLOSE_PROTOCOL_ERROR, f"Close code {code} is not allowed.")
    try:
        return code, payload[2:].decode("utf-8")
    except UnicodeDecodeError:
        raise ProtocolViolation(CLOSE_INVALID_DATA, "The close reason is not UTF-8.") from None


def _unmask(payload: bytes | bytearray, mask: bytes | bytearray) -> bytes:
    # XOR as one big integer: a handful of C calls, whatever the length.
    size = len(payload)
    if not size:
        return b""
    key = (mask * (size // 4 + 1))[:size]
    return (int.from_bytes(payload, "big") ^ int.from_bytes(key, "big")).to_bytes(size, "big")


class FrameParser:
    """Client frames in, whole messages out.

    `feed` the bytes as they arrive, then call `next` until it returns None. Control frames
    come out as they are found, even between the fragments of a data message.
    """

    def __init__(self, max_message: int) -> None:
        self.max_message = max_message
        self._buffer = bytearray()
        self._position = 0
        self._fragments: list[bytes] = []
        self._fragment_opcode: int | None = None
        self._fragment_size = 0

    def feed(self, data: bytes | bytearray) -> None:
        """Add received bytes."""
        if self._position and self._position >= len(self._buffer) // 2:
            del self._buffer[: self._position]
            self._position = 0
        self._buffer += data

    def has_data(self) -> bool:
        """Whether received bytes are waiting to be parsed (more frames may be in hand)."""
        return self._position < len(self._buffer)

    def next(self) -> Message | None:
        """The next whole message, or None until more bytes arrive.

        Raises `ProtocolViolation` for anything RFC 6455 says fails the connection.
        """
        # The usual frame first: a whole, masked text message of under 126 bytes, outside a
        # fragmented one. Its checks are the general path's, for that one header.
        buffer, start = self._buffer, self._position
        if (
            len(buffer) - start >= 6
            and buffer[start] == _WHOLE_TEXT
            and (second := buffer[start + 1]) & 0x80
            and (size := second & 0x7F) < 126
            and self._fragment_opcode is None
            and size <= self.max_message
        ):
            end = start + 6 + size
            if end <= len(buffer):
                self._position = end
                return Message(
                    OP_TEXT, _unmask(buffer[start + 6 : end], buffer[start + 2 : start + 6])
                )
        while True:
            frame = self._next_frame()
            if frame is None:
                return None
            fin, opcode, payload = frame
            if opcode >= OP_CLOSE:
                return Message(opcode, payload)
            if opcode == OP_CONTINUATION:
                if self._fragment_opcode is None:
                    raise ProtocolViolation(
                        CLOSE_PROTOCOL_ERROR, "A continuation frame without a message to continue."
                    )
            elif self._fragment_opcode is not None:
                raise ProtocolViolation(
                    CLOSE_PROTOCOL_ERROR, "A new message began before the last one ended."
                )
            elif fin:
                return Message(opcode, payload)
            else:
                self._fragment_opcode = opcode
            self._fragments.append(payload)
            self._fragment_size += len(payload)
            if fin:
                message = Message(self._fragment_opcode, b"".join(self._fragments))
                self._fragments.clear()
                self._fragment_opcode = None
                self._fragment_size = 0
                return message

    def _next_frame(self) -> tuple[bool, int, bytes] | None:
        buffer, start = self._buffer, self._position
        available = len(buffer) - start
        if available < 2:
            return None
        first, second = buffer[start], buffer[start + 1]
        if first & 0x70:
            raise ProtocolViolation(CLOSE_PROTOCOL_ERROR, "Reserved bits are set.")
        if not second & 0x80:
            raise ProtocolViolation(CLOSE_PROTOCOL_ERROR, "Client frames must be masked.")
        fin, opcode, size = bool(first & 0x80), first & 0x0F, second & 0x7F
        if opcode not in _DATA_OPCODES and opcode not in _CONTROL_OPCODES:
            raise ProtocolViolation(CLOSE_PROTOCOL_ERROR, f"Unknown opcode {opcode}.")
        header = 6
        if size == 126:
            header = 8
            if available < header:
                return None
            size = struct.unpack_from("!H", buffer, start + 2)[0]
        elif size == 127:
            header = 14
            if available < header:
                return None
            size = struct.unpack_from("!Q", buffer, start + 2)[0]
        if opcode >= OP_CLOSE and (size > 125 or not fin):
            raise ProtocolViolation(
                CLOSE_PROTOCOL_ERROR, "Control frames must be whole and at most 125 bytes."
            )
        if opcode < OP_CLOSE and self._fragment_size + size > self.max_message:
            raise ProtocolViolation(
                CLOSE_TOO_BIG, f"Messages are limited to {self.max_message} bytes."
            )
        if available < header + size:
            return None
        mask = buffer[start + header - 4 : start + header]
        payload = _unmask(buffer[start + header : start + header + size], mask)
        self._position = start + header + size
        return fin, opcode, payload
