"""Cameras attached to robots: a capture process each, frames read by a trio task.

Each camera's source runs in a process of its own (`capture.py`), so nothing it does in native
code (a device, FFmpeg, MuJoCo's OpenGL) can stall the server, its control loops or the e-stop.
A trio task asks it for a frame at a time and keeps the rate; the newest frame is kept for live
streams, and each subscriber (the recorder) gets the frames in a bounded drop-oldest queue.

A source that fails (a camera unplugged, a file gone, a renderer that hangs or dies) is reported
to the robot like a slave's fault, as a warning that never stops the arm, at once, and opened
again in a new process after 1 s, then 2, 4, up to 10.
"""

from __future__ import annotations

import contextlib
import re
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import trio

from arena.protocol.errors import ArenaError, ErrorCode, Severity
from arena.robot.events import CameraFrame
from arena.robot.handle import Robot
from arena.robot.mailbox import EventQueue
from arena.sensors.capture import CaptureProcess, Frame, Recipe, named_recipe
from arena.sensors.sources import scale_jpeg

NAME = re.compile(r"^[A-Za-z0-9_-]{1,32}$")
#: `twin` or `twin:SLAVE_ID`: the robot's physics slave, rendered (`arena.drivers.twin_camera`).
TWIN = re.compile(r"^twin(:[A-Za-z0-9_.-]{1,64})?$")
#: Rate and size when the body names none: a twin's frames cost ~130 ms each (specs/physics.md).
DEFAULTS = {"camera": (30, 640, 480), "twin": (5, 96, 96)}
#: Cameras one robot may have.
MAX_CAMERAS_PER_ROBOT = 4
RETRY_INITIAL, RETRY_MAX = 1.0, 10.0


@dataclass(frozen=True)
class CameraSpec:
    """What `POST /api/robots/{id}/cameras` asks for."""

    name: str
    source: str  # "test-pattern", "file:PATH", a V4L2 device such as /dev/video0, or "twin"
    fps: int = 30
    width: int = 640
    height: int = 480

    @classmethod
    def of(
        cls,
        name: str,
        source: str,
        fps: int | None = None,
        width: int | None = None,
        height: int | None = None,
    ) -> CameraSpec:
        """The spec with the defaults of its kind of source for what is not given."""
        default_fps, default_width, default_height = DEFAULTS[
            "twin" if TWIN.match(source) else "camera"
        ]
        return cls(
            name,
            source,
            default_fps if fps is None else fps,
            default_width if width is None else width,
            default_height if height is None else height,
        )

    @property
    def twin(self) -> str | None:
        """For a twin camera, the slave id it names ("" for the robot's only physics slave);
        None for any other source."""
        found = TWIN.match(self.source)
        return None if found is None else (found.group(1) or ":")[1:]

    def check(self) -> None:
        """Raise `ArenaError(INVALID_BODY)` for a spec no camera can have."""
        problems = []
        if not NAME.match(self.name):
            problems.append('"name" must be 1-32 letters, digits, "_" or "-"')
        if not (
            self.source == "test-pattern"
            or (self.source.startswith("file:") and len(self.source) > 5)
            or self.source.startswith("/dev/")
            or TWIN.match(self.source)
        ):
            problems.append(
                '"source" must be "test-pattern", "file:PATH", a /dev/video device, "twin" or '
                '"twin:SLAVE_ID"'
            )
        if not 1 <= self.fps <= 60:
            problems.append('"fps" must be 1 to 60')
        if not (16 <= self.width <= 1920 and 16 <= self.height <= 1080):
            problems.append('"width" must be 16-1920 and "height" 16-1080')
        elif self.width % 2 or self.height % 2:
            problems.append('"width" and "height" must be even (JPEG 4:2:0)')
        if problems:
            raise ArenaError(ErrorCode.INVALID_BODY, "Invalid camera: " + "; ".join(problems) + ".")


#: Frames being scaled at once, server-wide (`Camera.scaled`).
SCALING = trio.CapacityLimiter(1)

#: Says how to open a camera's source (at attach, and again after each failure); raises
#: `OSError` when it cannot be opened now (a twin whose physics slave is gone).
Opener = Callable[[], Recipe]


class Camera:
    """One camera of one robot: runs its capture process while `run` runs."""

    def __init__(self, robot: Robot, spec: CameraSpec, opener: Opener | None = None) -> None:
        self.robot = robot
        self.spec = spec
        #: Opens its source: at attach, and again after a failure.
        self.opener: Opener = opener or self._open_named
        self.sensor_id = f"camera:{spec.name}"
        self.latest: CameraFrame | None = None
        self.frames = 0  # frames delivered to trio
        self.dropped = 0  # frames a free-running device delivered that nobody took
        self.failures = 0
        self.error: str | None = None
        self.streams = 0  # live streams being served
        self.streams_dropped = 0  # streams ended because their client stopped reading
        self.closed = False
        self.finished = trio.Event()  # set once the capture process is gone
        self._seq = 0
        self._subscribers: set[EventQueue[CameraFrame]] = set()
        self._changed = trio.Event()
        self._scaled: tuple[tuple[int, int, int], bytes] | None = None

    def _open_named(self) -> Recipe:
        """How to open the source `spec.source` names."""
        return named_recipe(self.spec.source, self.spec.width, self.spec.height, self.spec.fps)

    def as_dict(self) -> dict[str, Any]:
        """What `GET .../cameras` shows of it."""
        return {
            "name": self.spec.name,
            "source": self.spec.source,
            "fps": self.spec.fps,
            "width": self.spec.width,
            "height": self.spec.height,
            "frames": self.frames,
            "dropped": self.dropped,
            "failures": self.failures,
            "error": self.error,
            "streams": self.streams,
            "stream": f"/api/robots/{self.robot.robot_id}/cameras/{self.spec.name}/stream",
        }

    @contextlib.contextmanager
    def subscribe(self, maxlen: int) -> Iterator[EventQueue[CameraFrame]]:
        """Every frame from now on, the oldest dropped past `maxlen`; closed with the camera."""
        queue: EventQueue[CameraFrame] = EventQueue(maxlen)
        self._subscribers.add(queue)
        if self.closed:
            queue.close()
        try:
            yield queue
        finally:
            self._subscribers.discard(queue)
            queue.close()

    async def next_frame(self, after: int) -> CameraFrame:
        """The newest frame once its `seq` is past `after` (latest wins: a slow reader skips
        frames); `trio.EndOfChannel` once the camera is gone."""
        while True:
            if self.closed:
                raise trio.EndOfChannel
            if self.latest is not None and self.latest.seq > after:
                return self.latest
            await self._changed.wait()

    async def scaled(self, frame: CameraFrame, width: int, height: int) -> bytes:
        """`frame` as a JPEG of `width` x `height` (the frame itself at its own size). Scaled
        in a thread, one at a time for the whole server: FFmpeg's JPEG codec works on bytes in
        memory and cannot block, but holds the interpreter for a few milliseconds a frame,
        so a client asking for many sizes at once waits its turn instead of starving the
        event loop; the newest scaled frame is kept for the next client that asks the same."""
        if (width, height) == (frame.width, frame.height):
            return frame.jpeg
        key = (frame.seq, width, height)
        cached = self._scaled
        if cached is not None and cached[0] == key:
            return cached[1]
        jpeg = await trio.to_thread.run_sync(scale_jpeg, frame.jpeg, width, height, limiter=SCALING)
        self._scaled = (key, jpeg)
        return jpeg

    async def run(
        self, process: CaptureProcess, *, task_status: Any = trio.TASK_STATUS_IGNORED
    ) -> None:
        """Capture from `process` (its source open) until cancelled or the robot stops."""
        task_status.started()
        try:
            async with trio.open_nursery() as nursery:
                nursery.start_soon(self._capture, process)
                await self.robot.stopped.wait()
                nursery.cancel_scope.cancel()
        finally:
            self.closed = True
            self._changed.set()
            for queue in list(self._subscribers):
                queue.close()
            self.finished.set()

    async def _capture(self, process: CaptureProcess | None) -> None:
        period = 1.0 / self.spec.fps
        delay = RETRY_INITIAL
        next_at = trio.current_time()
        try:
            while True:
                if process is None:
                    try:
                        process = await CaptureProcess.open(self.opener())
                    except OSError as exc:
                        self._failed(str(exc))
                        await trio.sleep(delay)
                        delay = min(delay * 2, RETRY_MAX)
                        continue
                    self._recovered()
                    next_at = trio.current_time()
                try:
                    frame = await process.read()
                except OSError as exc:
                    await process.close()
                    process = None
                    self._failed(str(exc))
                    await trio.sleep(delay)
                    delay = min(delay * 2, RETRY_MAX)
                    continue
                delay = RETRY_INITIAL
                self._deliver(frame)
                if process.paced:  # else the device keeps its own rate
                    # A source that fell behind by more than a frame starts afresh instead of
                    # bursting to catch up.
                    next_at = max(next_at, trio.current_time() - period) + period
                    await trio.sleep_until(next_at)
        finally:
            if process is not None:
                await process.close()

    def _deliver(self, frame: Frame) -> None:
        """Keep `frame` as the newest and hand it to every subscriber. Its `age` (from when its
        picture was taken: the twin's pose read, a device's delivery) dates it."""
        self.dropped += frame.dropped
        if self.closed:
            return
        age = max(0.0, frame.age)
        captured = CameraFrame(
            self.robot.robot_id,
            self.spec.name,
            self._seq,
            trio.current_time() - age,
            time.time() - age,
            self.spec.width,
            self.spec.height,
            frame.jpeg,
        )
        self._seq += 1
        self.frames += 1
        self.latest = captured
        for queue in self._subscribers:
            queue.put(captured)
        self._changed.set()
        self._changed = trio.Event()

    def _failed(self, message: str) -> None:
        self.failures += 1
        first = self.error is None
        self.error = message
        if first and not self.closed:
            self.robot.report_sensor_fault(
                self.sensor_id, ErrorCode.CAMERA_FAILED, f"{message} (retrying)", Severity.WARNING
            )

    def _recovered(self) -> None:
        if self.error is not None and not self.closed:
            self.error = None
            self.robot.report_sensor_fault(
                self.sensor_id, ErrorCode.CAMERA_RECOVERED, "capturing again", Severity.INFO
            )


class Cameras:
    """Every robot's cameras: attach, list, find, detach. Cameras run in `run`'s nursery."""

    def __init__(self) -> None:
        self._cameras: dict[tuple[str, str], tuple[Camera, trio.CancelScope]] = {}
        self._nursery: trio.Nursery | None = None
        #: Called with each camera attached (the recorder follows it).
        self.on_attach: list[Callable[[Camera], None]] = []

    async def run(self, *, task_status: Any = trio.TASK_STATUS_IGNORED) -> None:
        """Host the cameras until cancelled."""
        async with trio.open_nursery() as nursery:
            self._nursery = nursery
            task_status.started()
            await trio.sleep_forever()

    def of(self, robot_id: str) -> list[Camera]:
        """The robot's cameras, in the order they were attached."""
        return [camera for (rid, _), (camera, _) in self._cameras.items() if rid == robot_id]

    def get(self, robot_id: str, name: str) -> Camera:
        """The robot's camera `name`, or `ArenaError(UNKNOWN_CAMERA)`."""
        found = self._cameras.get((robot_id, name))
        if found is None:
            raise ArenaError(
                ErrorCode.UNKNOWN_CAMERA, f"Robot {robot_id!r} has no camera {name!r}."
            )
        return found[0]

    async def attach(self, robot: Robot, spec: CameraSpec, opener: Opener | None = None) -> Camera:
        """Open the camera's source (refused with CAMERA_FAILED if it cannot be) and start it.
        `opener` opens a source that `spec.source` alone cannot say how to (the twin's)."""
        spec.check()
        key = (robot.robot_id, spec.name)
        if key in self._cameras:
            raise ArenaError(
                ErrorCode.CAMERA_EXISTS, f"Robot {robot.robot_id!r} has a camera {spec.name!r}."
            )
        if len(self.of(robot.robot_id)) >= MAX_CAMERAS_PER_ROBOT:
            raise ArenaError(
                ErrorCode.CAMERA_EXISTS,
                f"Robot {robot.robot_id!r} has {MAX_CAMERAS_PER_ROBOT} cameras, the most it may.",
            )
        camera = Camera(robot, spec, opener)
        try:
            process = await CaptureProcess.open(camera.opener())
        except OSError as exc:
            raise ArenaError(
                ErrorCode.CAMERA_FAILED, f"Camera {spec.name!r} cannot capture: {exc}"
            ) from None
        if key in self._cameras or self._nursery is None:  # raced, or shutting down
            await process.close()
            raise ArenaError(
                ErrorCode.CAMERA_EXISTS, f"Robot {robot.robot_id!r} has a camera {spec.name!r}."
            )
        scope = trio.CancelScope()
        self._cameras[key] = (camera, scope)
        for callback in self.on_attach:
            callback(camera)
        await self._nursery.start(self._host, camera, process, scope)
        return camera

    async def detach(self, robot_id: str, name: str) -> None:
        """Stop the camera and forget it."""
        camera = self.get(robot_id, name)
        _, scope = self._cameras.pop((robot_id, name))
        scope.cancel()
        await camera.finished.wait()

    async def _host(
        self,
        camera: Camera,
        process: CaptureProcess,
        scope: trio.CancelScope,
        *,
        task_status: Any = trio.TASK_STATUS_IGNORED,
    ) -> None:
        try:
            with scope:
                await camera.run(process, task_status=task_status)
        finally:
            key = (camera.robot.robot_id, camera.spec.name)
            if key in self._cameras and self._cameras[key][0] is camera:
                del self._cameras[key]  # the robot stopped
