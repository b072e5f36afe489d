"""REST for cameras and episodes, and the cameras' live MJPEG streams.

The stream (`GET /api/robots/{id}/cameras/{name}/stream`) is served by the listener itself,
like the WebSockets, not by hypercorn: each part is written with a deadline, so a client that
stops reading loses its stream after `STREAM_SEND_TIMEOUT` instead of holding a slot for ever,
and it always gets the newest frame (latest wins; a slow client skips frames).

Never a backlog: after each part the stream waits until the kernel has handed it to the client
(the socket's unsent and unacknowledged bytes, `TIOCOUTQ`, at most `STREAM_QUEUE_BYTES`) before
taking the newest frame, so a slow client or link gets fewer frames, each fresh, instead of
every frame ever later (specs/remote-link.md, "Video keeps up").
"""

from __future__ import annotations

import fcntl
import struct
import termios
from collections.abc import Callable
from typing import Any, Protocol

import trio
from quart import Blueprint, Response, current_app, request

from arena.protocol.errors import ArenaError, ErrorCode
from arena.protocol.rest import CameraBody, EpisodeBody
from arena.protocol.ws_frames import UpgradeRequest
from arena.robot.episodes import Episode
from arena.server import parts
from arena.server.auth import authorize, refuse
from arena.server.base import STATUS_FOR, ArenaApp, read_body
from arena.server.identity import Role
from arena.server.listener import http_error

blueprint = Blueprint("sensors", __name__)

#: Live streams one camera serves at once.
MAX_STREAMS_PER_CAMERA = 8
#: A part not taken by the client within this long ends its stream.
STREAM_SEND_TIMEOUT = 5.0
BOUNDARY = "arenaframe"
#: A part is taken once at most this many of the stream's bytes wait in the kernel.
STREAM_QUEUE_BYTES = 8 * 1024
#: How often a stream whose client is behind looks again.
STREAM_DRAIN_POLL = 0.01


def _app() -> ArenaApp:
    return current_app  # type: ignore[return-value]


@blueprint.get("/api/robots/<robot_id>/cameras")
async def list_cameras(robot_id: str) -> dict[str, Any]:
    """The robot's cameras with their counters."""
    app = _app()
    app.manager.get(robot_id)
    return {"cameras": [camera.as_dict() for camera in app.cameras.of(robot_id)]}


@blueprint.post("/api/robots/<robot_id>/cameras")
async def attach_camera(robot_id: str) -> tuple[dict[str, Any], int]:
    """Attach a camera; its source is opened first, so a wrong device fails here."""
    app = _app()
    robot = app.manager.get(robot_id)
    body: CameraBody = await read_body(CameraBody)
    camera = await parts.attach_camera(app, robot, body)
    return camera.as_dict(), 201


@blueprint.get("/api/robots/<robot_id>/cameras/<name>")
async def read_camera(robot_id: str, name: str) -> dict[str, Any]:
    """One camera."""
    return _app().cameras.get(robot_id, name).as_dict()


@blueprint.delete("/api/robots/<robot_id>/cameras/<name>")
async def detach_camera(robot_id: str, name: str) -> dict[str, Any]:
    """Stop a camera and forget it (what it recorded stays recorded)."""
    app = _app()
    await app.cameras.detach(robot_id, name)
    return {"detached": name}


#: The largest side a frame may be scaled to (`?width=&height=`).
MAX_SCALED_SIDE = 4096


def _scaled_size(args: Any) -> tuple[int, int] | None:
    """`?width=W&height=H` (both or neither; even numbers, as JPEG's 4:2:0 needs them), else
    None; `INVALID_VALUE` with the reason."""
    given = [args.get(name) for name in ("width", "height")]
    if given == [None, None]:
        return None
    # ASCII digits only, and short: str.isdigit() accepts "²" and int() refuses huge strings.
    if not all(v is not None and v.isascii() and v.isdigit() and len(v) <= 5 for v in given):
        raise ArenaError(
            ErrorCode.INVALID_VALUE,
            '"width" and "height" are given together, as whole numbers of pixels.',
        )
    width, height = (int(value) for value in given)
    if not (2 <= width <= MAX_SCALED_SIDE and 2 <= height <= MAX_SCALED_SIDE) or (
        width % 2 or height % 2
    ):
        raise ArenaError(
            ErrorCode.INVALID_VALUE,
            f'"width" and "height" are even numbers from 2 to {MAX_SCALED_SIDE} '
            f"(given {width} x {height}).",
        )
    return width, height


@blueprint.get("/api/robots/<robot_id>/cameras/<name>/frame")
async def camera_frame(robot_id: str, name: str) -> Response:
    """The newest frame as one JPEG, at the camera's size or scaled to `?width=&height=` (a
    policy's input size: what a remote policy fetches, so less travels)."""
    size = _scaled_size(request.args)
    camera = _app().cameras.get(robot_id, name)
    with trio.move_on_after(2.0):
        frame = await camera.next_frame(-1)
        jpeg = frame.jpeg if size is None else await camera.scaled(frame, *size)
        response = Response(jpeg, mimetype="image/jpeg")
        response.headers["Cache-Control"] = "no-store"
        response.headers["X-Frame-Seq"] = str(frame.seq)
        return response
    raise ArenaError(ErrorCode.CAMERA_FAILED, f"Camera {name!r} has no frame yet.")


@blueprint.get("/api/robots/<robot_id>/cameras/<name>/stream")
async def stream_elsewhere(robot_id: str, name: str) -> Response:
    """The stream asked on a connection that served other requests before (a browser reuses
    its connections): the listener serves streams only as a connection's first request, so
    send the client to the same address on a fresh connection."""
    _app().cameras.get(robot_id, name)
    response = Response("", status=307)
    response.headers["Location"] = request.full_path if request.query_string else request.path
    response.headers["Connection"] = "close"
    return response


def _episode(episode: Episode) -> dict[str, Any]:
    return {
        "index": episode.index,
        "task": episode.task,
        "duration": None if episode.ended is None else round(episode.ended - episode.started, 3),
        "discarded": episode.discarded,
    }


@blueprint.get("/api/robots/<robot_id>/episodes")
async def episodes(robot_id: str) -> dict[str, Any]:
    """The running episode, the last one, and how many were kept and discarded."""
    robot = _app().manager.get(robot_id)
    return robot.episodes.as_dict(trio.current_time())


@blueprint.post("/api/robots/<robot_id>/episodes/start")
async def start_episode(robot_id: str) -> tuple[dict[str, Any], int]:
    """Start an episode with its task (marked in the recording)."""
    robot = _app().manager.get(robot_id)
    body: EpisodeBody = await read_body(EpisodeBody)
    return _episode(await robot.episode("start", body.task)), 201


@blueprint.post("/api/robots/<robot_id>/episodes/stop")
async def stop_episode(robot_id: str) -> dict[str, Any]:
    """End the running episode and keep it."""
    robot = _app().manager.get(robot_id)
    return _episode(await robot.episode("stop"))


@blueprint.post("/api/robots/<robot_id>/episodes/discard")
async def discard_episode(robot_id: str) -> dict[str, Any]:
    """End the running episode without keeping it (or take back the last one kept)."""
    robot = _app().manager.get(robot_id)
    return _episode(await robot.episode("discard"))


@blueprint.post("/api/robots/<robot_id>/highlight")
async def highlight(robot_id: str) -> tuple[dict[str, Any], int]:
    """Save the last seconds a policy's highlight strategy keeps as a kept episode."""
    robot = _app().manager.get(robot_id)
    driver = robot.master_driver()
    save = getattr(driver, "highlight", None)
    if save is None:
        raise ArenaError(
            ErrorCode.NO_HIGHLIGHT,
            "The robot's master is no policy Arena runs with the highlight strategy: nothing "
            "is kept to save.",
        )
    episode: Episode = await save()
    return _episode(episode), 201


# -- the MJPEG stream, served by the listener --------------------------------------------------


def stream_route(app: ArenaApp) -> Any:
    """The listener's route for camera streams: a handler for the stream's path, else None."""

    def route(request: UpgradeRequest) -> Any:
        parts = request.path.split("/")
        if not (
            len(parts) == 7
            and parts[1:3] == ["api", "robots"]
            and parts[4] == "cameras"
            and parts[6] == "stream"
        ):
            return None
        return lambda stream: _serve_stream(app, request, parts[3], parts[5], stream)

    return route


async def _serve_stream(
    app: ArenaApp, request: UpgradeRequest, robot_id: str, name: str, stream: trio.abc.Stream
) -> None:
    headers = request.headers
    try:
        app.origin_policy.check("GET", headers.get("origin"), headers.get("host"), request.scheme)
        principal = authorize(
            app,
            headers.get("authorization"),
            request.args.get("token"),
            Role.VIEWER,
            "A stream",
            True,
        )
        if not app.access.sees(principal, robot_id):
            refuse(app, "scope")
            raise ArenaError(ErrorCode.UNKNOWN_ROBOT, f"No robot with id {robot_id!r}.")
        camera = app.cameras.get(robot_id, name)
        if camera.streams >= MAX_STREAMS_PER_CAMERA:
            raise ArenaError(
                ErrorCode.OVERLOADED,
                f"Camera {name!r} serves {MAX_STREAMS_PER_CAMERA} streams already.",
            )
    except ArenaError as refusal:
        status = STATUS_FOR.get(refusal.code, 400)
        await stream.send_all(http_error(f"{status} Refused", refusal.message, refusal.code))
        return
    camera.streams += 1
    try:
        await send_frames(camera, stream, kernel_queue(stream))
    finally:
        camera.streams -= 1


class FrameSource(Protocol):
    """What a stream needs of a camera."""

    streams_dropped: int

    async def next_frame(self, after: int) -> Any:
        """The newest frame past `after` (with `seq`, `wall_time`, `jpeg`)."""


def kernel_queue(stream: trio.abc.Stream) -> Callable[[], int] | None:
    """How many bytes written to `stream` the kernel holds still (unsent or unacknowledged:
    Linux's TIOCOUTQ), or None where it cannot tell (another system, a stream with no
    socket)."""
    transport: Any = stream
    while not hasattr(transport, "socket") and hasattr(transport, "transport_stream"):
        transport = transport.transport_stream  # TLS
    sock = getattr(transport, "socket", None)
    if sock is None or not hasattr(termios, "TIOCOUTQ"):
        return None

    def queued() -> int:
        fd = sock.fileno()
        if fd < 0:
            return 0
        answer = fcntl.ioctl(fd, termios.TIOCOUTQ, b"\0\0\0\0")
        return int(struct.unpack("i", answer)[0])

    try:
        queued()
    except OSError:
        return None
    return queued


async def _drained(queued: Callable[[], int]) -> None:
    """Until the kernel holds at most `STREAM_QUEUE_BYTES` of the stream."""
    while queued() > STREAM_QUEUE_BYTES:
        await trio.sleep(STREAM_DRAIN_POLL)


async def send_frames(
    camera: FrameSource, stream: trio.abc.Stream, queued: Callable[[], int] | None
) -> None:
    """Serve the multipart stream: the newest frame each time the client has taken the last
    (`queued`: the kernel's bytes of the stream; None: as fast as the stream takes them)."""
    await stream.send_all(
        b"HTTP/1.1 200 OK\r\nContent-Type: multipart/x-mixed-replace; boundary="
        + BOUNDARY.encode()
        + b"\r\nCache-Control: no-store\r\nConnection: close\r\n\r\n"
    )
    seq = -1
    while True:
        try:
            frame = await camera.next_frame(seq)
        except trio.EndOfChannel:  # the camera was detached
            return
        seq = frame.seq
        part = (
            f"--{BOUNDARY}\r\nContent-Type: image/jpeg\r\nContent-Length: {len(frame.jpeg)}\r\n"
            f"X-Frame-Seq: {frame.seq}\r\nX-Timestamp: {frame.wall_time:.6f}\r\n\r\n"
        ).encode("latin-1")
        with trio.move_on_after(STREAM_SEND_TIMEOUT) as late:
            await stream.send_all(part + frame.jpeg + b"\r\n")
            if queued is not None:
                await _drained(queued)
        if late.cancelled_caught:
            camera.streams_dropped += 1
            return
