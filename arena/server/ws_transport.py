"""One server-side WebSocket on a trio stream: receive messages, send text, close.

A message is written at once when the socket is idle and the reader has no more frames in
hand (the lowest latency). Otherwise it goes to an outbox that a writer task empties with one
`send_all` per burst, so the answers to a burst of commands share one system call.

Once a peer has let more than `high_water` bytes pile up, `offer` refuses more (the caller
decides what to drop, see `ws.backpressure`) and `send` waits for room; a reader never
waits on writing. Pongs owed to a peer that does not read are kept to the newest one, and
control frames count toward the reader's fair share like data frames, so a ping flood costs
the flooder its own turn and bounded memory.

On a plain TCP socket the transport reads and writes the file descriptor itself and waits
only when the kernel says it would block: trio's socket calls end every read and write with a
trip through the scheduler, which with many quiet connections cost more than the messages.
It waits after a read that left the socket empty (EAGAIN, or a read shorter than asked), with
the listener's `ReadPoller` when there is one, else on trio. Other streams (TLS) go through
trio's stream calls.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Callable

import trio

from arena.protocol import ws_frames
from arena.protocol.ws_frames import (
    OP_BINARY,
    OP_CLOSE,
    OP_PING,
    OP_PONG,
    OP_TEXT,
    FrameParser,
    ProtocolViolation,
    UpgradeRequest,
    WebSocketClosed,
)
from arena.server.read_poller import ReadPoller

RECEIVE_BYTES = 65536
#: Frames received in a row before the reader lets other tasks run.
_FAIRNESS_BATCH = 32


class _Handled:
    """What `WebSocket._take` returns for a frame it dealt with itself (a ping, a close)."""


_HANDLED = _Handled()


#: The text last framed (None before any: "" is interned, so it cannot stand for none) and
#: its frame.
_last_frame: tuple[str | None, bytes] = (None, b"")


def _frame(text: str) -> bytes:
    """A text frame; the same text object as last time (the acks of a burst, encoded once a
    millisecond) is framed once."""
    global _last_frame
    if text is not _last_frame[0]:
        _last_frame = (text, ws_frames.encode_frame(OP_TEXT, text.encode("utf-8")))
    return _last_frame[1]


def _frames(texts: tuple[str, ...]) -> bytes:
    return _frame(texts[0]) if len(texts) == 1 else b"".join(map(_frame, texts))


class WebSocket:
    """An accepted WebSocket. Run `run_writer` beside the handler; `finish` when done."""

    def __init__(
        self,
        stream: trio.abc.Stream,
        request: UpgradeRequest,
        *,
        max_message: int,
        high_water: int = 16 * 1024,
        poller: ReadPoller | None = None,
    ) -> None:
        self.request = request
        self._stream = stream
        # The socket of a plain TCP stream (trio keeps it non-blocking), else None.
        self._socket = stream.socket if isinstance(stream, trio.SocketStream) else None
        self._poller = poller
        self._may_hold_more = True  # more may be waiting (a full read, or a wake-up): read first
        self._parser = FrameParser(max_message)
        self._outbox: list[bytes] = []
        self._outbox_bytes = 0
        self.high_water = high_water
        self._writer_lot = trio.lowlevel.ParkingLot()
        self._drained_lot = trio.lowlevel.ParkingLot()
        self._received_in_a_row = 0
        self._owed_pong: bytes | None = None  # the newest ping's payload, while backlogged
        #: Pongs not sent because a newer ping came while the peer was not reading.
        self.pongs_dropped = 0
        self._finishing = False
        self._sending = False  # a send_all is under way (the writer's or a direct one)
        #: Set once a close frame is sent (or the stream is gone): nothing more goes out.
        self.close_sent = False
        #: Set once the peer's close frame or the end of the stream is seen.
        self.closed_by_peer: WebSocketClosed | None = None
        self.broken = False
        self._failed = False
        self._owed_close: tuple[int, str] | None = None  # (code, reason) of the close to send
        #: Told each pong's payload (a master's link times the server's pings with it).
        self.on_pong: Callable[[bytes], None] | None = None

    # -- receiving ------------------------------------------------------------------------------

    def feed(self, data: bytes) -> None:
        """Bytes that arrived with the handshake."""
        self._parser.feed(data)

    async def receive(self) -> str | bytes:
        """The next data message: `str` for text, `bytes` for binary.

        Pings are answered on the way. Raises `WebSocketClosed` once the peer closes, the
        stream ends, or the peer breaks the protocol (which is answered with a close frame).
        """
        while True:
            if self._received_in_a_row >= _FAIRNESS_BATCH:  # control frames count too
                self._received_in_a_row = 0
                await trio.lowlevel.checkpoint()
            message = self._take()
            if message is None:
                await self._receive_more()
            elif not isinstance(message, _Handled):
                return message

    def next_in_hand(self) -> str | bytes | None:
        """The next data message if its bytes are in hand already, else None. Never waits,
        so a reader can take the rest of a burst at once and answer it in one write.

        None too once the reader has taken as many frames in a row as it may before letting
        other tasks run, and once the peer's close (or a violation) is found: the close frame
        that answers it waits for the reader's next `receive`, so that it follows the answers
        to everything sent before it."""
        while self._received_in_a_row < _FAIRNESS_BATCH and self.closed_by_peer is None:
            message = self._take()
            if not isinstance(message, _Handled):
                return message
        return None

    def _take(self) -> str | bytes | _Handled | None:
        """One frame in hand: a data message, `_HANDLED` (a control frame answered, or the
        peer's close or a violation noted), or None if no whole frame is in hand. Once the
        peer has closed, sends the close frame owed to it and raises `WebSocketClosed`."""
        if self.closed_by_peer is not None:
            if self._owed_close is not None:
                self._send_close(*self._owed_close)
                self._owed_close = None
            raise self.closed_by_peer
        try:
            message = self._parser.next()
        except ProtocolViolation as violation:
            self._fail(violation.code, violation.reason)
            return _HANDLED
        if message is None:
            return None
        self._received_in_a_row += 1
        if message.opcode == OP_TEXT:
            try:
                return message.payload.decode("utf-8")
            except UnicodeDecodeError:
                self._fail(ws_frames.CLOSE_INVALID_DATA, "Text frames must be UTF-8.")
        elif message.opcode == OP_BINARY:
            return message.payload
        elif message.opcode == OP_PING:
            self._pong(message.payload)
        elif message.opcode == OP_PONG:
            if self.on_pong is not None:
                self.on_pong(message.payload)
        elif message.opcode == OP_CLOSE:
            try:
                code, reason = ws_frames.parse_close(message.payload)
            except ProtocolViolation as violation:
                self._fail(violation.code, violation.reason)
            else:
                # Echo the close (RFC 6455 5.5.1), with the code unless the peer gave none.
                self._owed_close = (1000 if code == 1005 else code, "")
                self.closed_by_peer = WebSocketClosed(code, reason)
        return _HANDLED

    async def _receive_more(self) -> None:
        try:
            if self._socket is None:
                self._received_in_a_row = 0
                data = await self._stream.receive_some(RECEIVE_BYTES)
            else:
                data = await self._read_socket(self._socket)
        except (trio.BrokenResourceError, trio.ClosedResourceError):
            data = b""
        if not data:
            self.closed_by_peer = WebSocketClosed(1006, "connection lost")
            self._set_broken()
            return
        self._parser.feed(data)

    async def _read_socket(self, sock: trio.socket.SocketType) -> bytes:
        while True:
            fd = sock.fileno()  # -1 once closed: never a number reused by another socket
            if fd < 0:
                return b""
            if self._may_hold_more:
                try:
                    data = os.read(fd, RECEIVE_BYTES)
                except BlockingIOError:
                    pass
                except OSError:  # reset by the peer
                    return b""
                else:
                    # A short read took all the kernel held: the next read waits for more,
                    # which saves the read that would only find the socket empty.
                    self._may_hold_more = len(data) == RECEIVE_BYTES or not data
                    return data
            self._received_in_a_row = 0  # waiting lets every other task run
            if self._poller is None:
                await trio.lowlevel.wait_readable(sock)
            else:
                await self._poller.wait_readable(sock)
            self._may_hold_more = True

    def _pong(self, payload: bytes) -> None:
        """Answer a ping; while the peer is behind, only the newest ping is answered
        (RFC 6455 5.5.3 allows answering just the most recent one)."""
        if not self.backlogged:
            self._queue(ws_frames.encode_frame(OP_PONG, payload))
            return
        if self._owed_pong is not None:
            self.pongs_dropped += 1
        self._owed_pong = payload

    def _fail(self, code: int, reason: str) -> None:
        """The peer broke the protocol: the close frame saying so goes out with the reader's
        next `receive` (see `next_in_hand`), and nothing more is read."""
        self._owed_close = (code, reason)
        self.closed_by_peer = WebSocketClosed(code, reason)
        self._failed = True

    # -- sending --------------------------------------------------------------------------------

    def ping_nowait(self, payload: bytes) -> None:
        """Queue a ping (its pong goes to `on_pong`); none to a peer that is behind, whose
        pong would time its backlog rather than the link."""
        if not self.backlogged:
            self._queue(ws_frames.encode_frame(OP_PING, payload))

    def send_nowait(self, text: str) -> None:
        """Queue a text message (dropped silently once the connection is closing)."""
        self._queue(ws_frames.encode_frame(OP_TEXT, text.encode("utf-8")))

    def holds_more(self) -> bool:
        """Bytes of further frames are in hand (the peer sent a burst)."""
        return self._parser.has_data()

    def send_now(self, *texts: str) -> bool:
        """Write text messages at once if nothing else is under way on a plain TCP socket;
        False (and nothing done) otherwise. Never waits: the caller may be a robot's actor."""
        if self._socket is None or not self._idle():
            return False
        self._write_socket(self._socket, _frames(texts))
        return True

    @property
    def queued_bytes(self) -> int:
        """Bytes waiting for the peer to read (what this connection holds in memory)."""
        return self._outbox_bytes

    @property
    def backlogged(self) -> bool:
        """The peer has let more than `high_water` bytes pile up."""
        return self._outbox_bytes > self.high_water and not self.close_sent

    def offer(self, *texts: str, whole: bool = False) -> bool:
        """Send text messages unless the peer is backlogged (then False, nothing queued).

        Never waits: a reader answering a burst of messages keeps the whole burst for one
        write, and a peer that stops reading never stalls the reader. `whole`: these answer
        all the frames the reader took together, so they go out at once (nothing else being
        queued) even with more frames in hand, without a hop to the writer task.
        """
        if self.backlogged:
            return False
        if self._socket is not None and (self._writable() if whole else self._idle()):
            self._write_socket(self._socket, _frames(texts))
        else:  # busy, or a stream (TLS) that only the writer task writes to
            self._queue(_frames(texts))
        return True

    async def send(self, *texts: str) -> None:
        """Send text messages, first waiting while the peer is backlogged (for writer tasks
        whose messages must not be dropped, such as a slave's targets). Unlike most trio
        calls it yields only when it has to wait."""
        await self.wait_for_room()
        self.offer(*texts)

    async def wait_for_room(self) -> None:
        """Until the peer is no longer backlogged (or the connection is closing)."""
        while self.backlogged:
            await self._drained_lot.park()

    async def wait_drained(self) -> None:
        """Until everything queued is handed to the kernel (or the connection is closing)."""
        while (self._outbox or self._sending) and not self.close_sent:
            await self._drained_lot.park()

    def _idle(self) -> bool:
        """Nothing queued or being written, and no more frames in hand to answer first."""
        return self._writable() and not self._parser.has_data()

    def _writable(self) -> bool:
        """Nothing queued or being written (a write now keeps the order)."""
        return not (self._sending or self._outbox or self.close_sent)

    def _write_socket(self, sock: trio.socket.SocketType, frame: bytes) -> None:
        try:
            written = os.write(sock.fileno(), frame)  # -1 once closed: EBADF
        except BlockingIOError:
            written = 0
        except OSError:  # the peer is gone: the reader sees the end of the stream
            self._set_broken()
            return
        if written < len(frame):
            self._queue(frame[written:])  # the kernel's buffer is full: the writer waits

    def close_nowait(self, code: int, reason: str = "") -> None:
        """Send a close frame once; everything queued before it still goes out."""
        self._send_close(code, reason)

    def _send_close(self, code: int, reason: str) -> None:
        if not self.close_sent:
            self._queue(ws_frames.encode_close(code, reason))
            self.close_sent = True

    def _queue(self, frame: bytes) -> None:
        if self.close_sent:
            return
        self._outbox.append(frame)
        self._outbox_bytes += len(frame)
        if self._writer_lot:
            self._writer_lot.unpark()

    async def run_writer(self) -> None:
        """Write whatever is queued, a burst per system call, until `finish` and drained."""
        while True:
            if self.broken or (self._finishing and not self._outbox and not self._sending):
                return
            if not self._outbox or self._sending:
                self._drained_lot.unpark_all()
                await self._writer_lot.park()
                continue
            data = b"".join(self._outbox) if len(self._outbox) > 1 else self._outbox[0]
            self._outbox.clear()
            self._outbox_bytes = 0
            self._drained_lot.unpark_all()
            await self._write(data)
            if self._owed_pong is not None:  # the peer reads again: answer its newest ping
                pong, self._owed_pong = self._owed_pong, None
                self._queue(ws_frames.encode_frame(OP_PONG, pong))

    async def _write(self, data: bytes) -> None:
        """One `send_all` under the `_sending` flag; a vanished peer marks the socket broken."""
        self._sending = True
        try:
            await self._stream.send_all(data)
        except (trio.BrokenResourceError, trio.ClosedResourceError):
            self._set_broken()
        finally:
            self._sending = False

    def _set_broken(self) -> None:
        self.broken = True
        self.close_sent = True
        self._outbox.clear()
        self._outbox_bytes = 0
        self._drained_lot.unpark_all()
        self._writer_lot.unpark_all()

    def finish(self) -> None:
        """No more messages: the writer ends once the outbox is empty."""
        self._finishing = True
        self._writer_lot.unpark_all()

    async def wait_for_peer_close(self, timeout: float) -> None:
        """After our close frame, read (and drop) until the peer's close or end of stream.

        After a protocol error the frames cannot be parsed any more: raw bytes are dropped
        instead, so a peer still sending (a frame over the size cap) reads our close frame
        rather than a reset connection.
        """
        with trio.move_on_after(timeout):
            with contextlib.suppress(WebSocketClosed):
                while not self._failed:
                    await self.receive()
            if not self._failed:
                # The peer's close frame (or the end of its stream) is in: the server closes
                # the TCP connection first (RFC 6455 7.1.1). Waiting for the peer's end of
                # stream here kept every client that waits for ours (`websockets` does) for
                # the whole timeout.
                return
            with contextlib.suppress(trio.BrokenResourceError, trio.ClosedResourceError):
                while not self.broken and await self._stream.receive_some(RECEIVE_BYTES):
                    pass
