"""Cameras attached to robots: a capture thread each, frames handed to trio through its token.

The capture thread only reads its source (`sources.py`) and keeps the rate; everything else
happens in trio, in the order frames arrive: the newest frame is kept for live streams, and
each subscriber (the recorder) gets the frames in a bounded drop-oldest queue. At most
`MAX_IN_FLIGHT` frames wait for trio: a busy server loses frames (counted), never memory.

A source that fails (a camera unplugged, a file gone) is reported to the robot like a slave's
fault, as a warning that never stops the arm, and reopened after 1 s, then 2, 4, up to 10.
"""

from __future__ import annotations

import contextlib
import re
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import trio

from arena.protocol.errors import ArenaError, ErrorCode, Severity
from arena.robot.events import CameraFrame
from arena.robot.handle import Robot
from arena.robot.mailbox import EventQueue
from arena.sensors.sources import FrameSource, open_source, pace

NAME = re.compile(r"^[A-Za-z0-9_-]{1,32}$")
#: `twin` or `twin:SLAVE_ID`: the robot's physics slave, rendered (`arena.drivers.twin_camera`).
TWIN = re.compile(r"^twin(:[A-Za-z0-9_.-]{1,64})?$")
#: Rate and size when the body names none: a twin's frames cost ~130 ms each (specs/physics.md).
DEFAULTS = {"camera": (30, 640, 480), "twin": (5, 96, 96)}
#: Cameras one robot may have.
MAX_CAMERAS_PER_ROBOT = 4
#: Frames captured but not yet taken by trio; beyond it the capture thread drops frames.
MAX_IN_FLIGHT = 2
RETRY_INITIAL, RETRY_MAX = 1.0, 10.0
#: How long a stopping camera waits for its thread (a device stuck in a read is abandoned).
JOIN_TIMEOUT = 2.0


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


#: Opens a camera's source (in a worker or the capture thread); raises `OSError` if it cannot.
Opener = Callable[[], FrameSource]


class Camera:
    """One camera of one robot: runs its capture thread while `run` runs."""

    def __init__(self, robot: Robot, spec: CameraSpec, opener: Opener | None = None) -> None:
        self.robot = robot
        self.spec = spec
        #: Opens its source: at attach, and again after a failure.
        self.opener: Opener = opener or self._open_named
        self.sensor_id = f"camera:{spec.name}"
        self.latest: CameraFrame | None = None
        self.frames = 0  # frames delivered to trio
        self.dropped = 0  # frames the capture thread dropped because trio had not taken two
        self.failures = 0
        self.error: str | None = None
        self.streams = 0  # live streams being served
        self.streams_dropped = 0  # streams ended because their client stopped reading
        self.closed = False
        self.finished = trio.Event()  # set once the capture thread is done
        self._seq = 0
        self._subscribers: set[EventQueue[CameraFrame]] = set()
        self._changed = trio.Event()
        self._stop = threading.Event()
        self._in_flight = threading.Semaphore(MAX_IN_FLIGHT)

    def _open_named(self) -> FrameSource:
        """The source `spec.source` names, opened."""
        return open_source(self.spec.source, self.spec.width, self.spec.height, self.spec.fps)

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

    async def run(
        self, source: FrameSource, *, task_status: Any = trio.TASK_STATUS_IGNORED
    ) -> None:
        """Capture from `source` (already open) until cancelled or the robot stops."""
        token = trio.lowlevel.current_trio_token()
        thread = threading.Thread(
            target=self._capture,
            args=(source, token),
            name=f"camera {self.robot.robot_id}/{self.spec.name}",
            daemon=True,  # a device stuck in a read must not keep the process alive
        )
        thread.start()
        task_status.started()
        try:
            await self.robot.stopped.wait()
        finally:
            self._stop.set()
            self.closed = True
            self._changed.set()
            for queue in list(self._subscribers):
                queue.close()
            with trio.CancelScope(shield=True):
                await trio.to_thread.run_sync(thread.join, JOIN_TIMEOUT)
            self.finished.set()

    # -- the capture thread -----------------------------------------------------------------

    def _capture(self, source: FrameSource | None, token: trio.lowlevel.TrioToken) -> None:
        period = 1.0 / self.spec.fps
        delay = RETRY_INITIAL
        next_at = time.perf_counter()
        try:
            while not self._stop.is_set():
                if source is None:
                    try:
                        source = self.opener()
                    except OSError as exc:
                        self._hand_to_trio(token, self._failed, str(exc))
                        self._stop.wait(delay)
                        delay = min(delay * 2, RETRY_MAX)
                        continue
                    self._hand_to_trio(token, self._recovered)
                    next_at = time.perf_counter()
                try:
                    jpeg = source.read()
                except OSError as exc:
                    source.close()
                    source = None
                    self._hand_to_trio(token, self._failed, str(exc))
                    self._stop.wait(delay)
                    delay = min(delay * 2, RETRY_MAX)
                    continue
                delay = RETRY_INITIAL
                # A source that knows when its picture was taken says so (the twin: when it read
                # the pose, before ~130 ms of rendering); else the frame is as old as its read.
                captured = getattr(source, "exposed", None) or time.perf_counter()
                if self._in_flight.acquire(blocking=False):
                    if not self._hand_to_trio(token, self._deliver, jpeg, captured):
                        return
                else:
                    self.dropped += 1
                if source.paced:
                    wait, next_at = pace(next_at, period)
                    self._stop.wait(wait)
        finally:
            if source is not None:
                source.close()

    def _hand_to_trio(
        self, token: trio.lowlevel.TrioToken, call: Callable[..., None], *args: Any
    ) -> bool:
        """Run `call` in trio soon; False once trio has finished."""
        try:
            token.run_sync_soon(call, *args)
        except trio.RunFinishedError:
            self._stop.set()
            return False
        return True

    # -- in trio ----------------------------------------------------------------------------

    def _deliver(self, jpeg: bytes, captured: float) -> None:
        self._in_flight.release()
        if self.closed:
            return
        age = max(0.0, time.perf_counter() - captured)
        frame = CameraFrame(
            self.robot.robot_id,
            self.spec.name,
            self._seq,
            trio.current_time() - age,
            time.time() - age,
            self.spec.width,
            self.spec.height,
            jpeg,
        )
        self._seq += 1
        self.frames += 1
        self.latest = frame
        for queue in self._subscribers:
            queue.put(frame)
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
            source = await trio.to_thread.run_sync(camera.opener)
        except OSError as exc:
            raise ArenaError(
                ErrorCode.CAMERA_FAILED, f"Camera {spec.name!r} cannot capture: {exc}"
            ) from None
        if key in self._cameras or self._nursery is None:  # raced, or shutting down
            source.close()
            raise ArenaError(
                ErrorCode.CAMERA_EXISTS, f"Robot {robot.robot_id!r} has a camera {spec.name!r}."
            )
        scope = trio.CancelScope()
        self._cameras[key] = (camera, scope)
        for callback in self.on_attach:
            callback(camera)
        await self._nursery.start(self._host, camera, source, scope)
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
        source: FrameSource,
        scope: trio.CancelScope,
        *,
        task_status: Any = trio.TASK_STATUS_IGNORED,
    ) -> None:
        try:
            with scope:
                await camera.run(source, task_status=task_status)
        finally:
            key = (camera.robot.robot_id, camera.spec.name)
            if key in self._cameras and self._cameras[key][0] is camera:
                del self._cameras[key]  # the robot stopped
