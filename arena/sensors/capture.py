"""A camera's source in a process of its own: the capture process, and the server's side of it.

Whatever a source does in native code (FFmpeg reading a device, MuJoCo rendering through
OpenGL, a vendor's SDK) it does in `python -m arena.sensors.capture`, a child of the server: a
source that hangs there, holding its interpreter's lock, stalls its own process and nothing
else, so the control loop and the e-stop go on. The server asks for one frame at a time over
the child's stdin and stdout and gives each answer `READ_TIMEOUT` seconds: a child that takes
longer is killed, and the camera reports it and starts another (`camera.py`).

What the child opens is a `Recipe`: an importable factory (`module:callable`, always chosen by
the server, never by a client) with its parameters, plus bytes only the server has at attach
time (the twin's compiled model) and, before each frame, bytes it reads then (the twin's pose).

The pipe carries length-prefixed msgpack frames of the structs below and nothing else (nothing
is pickled). A child whose server is gone ends by itself within a second, unless it is stuck in
native code holding its interpreter's lock: a planned stop kills every child, and a service's
stop (systemd) kills the whole control group.
"""

from __future__ import annotations

import importlib
import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import IO, Any, TypeAlias

import msgspec
import trio

from arena.child import Child
from arena.protocol import frames
from arena.protocol.frames import HEADER, FrameError

#: Seconds a child has to start, import its source's libraries and open it.
OPEN_TIMEOUT = 30.0
#: Seconds a frame may take before the child is taken for stuck and killed.
READ_TIMEOUT = 10.0
#: The largest frame either side accepts (a compiled model with its meshes is the biggest).
MAX_FRAME = 64 * 1024 * 1024
#: OpenGL backends MuJoCo can render headless with, tried in this order after `MUJOCO_GL`'s.
GL_BACKENDS = ("egl", "osmesa")


class Open(msgspec.Struct, tag="open", frozen=True):
    """Open the source `factory(**params, blob=blob)` makes."""

    factory: str
    params: dict[str, Any]
    blob: bytes = b""


class Read(msgspec.Struct, tag="read", frozen=True):
    """The next frame; `feed` is handed to the source first (the twin's pose), if any."""

    feed: bytes = b""


class Opened(msgspec.Struct, tag="opened", frozen=True):
    """The source is open; `paced`: it answers at once, so the server keeps the rate (else it
    is a device delivering at its own)."""

    paced: bool = True


class Frame(msgspec.Struct, tag="frame", frozen=True):
    """A frame as JPEG; `age`: seconds from when its picture was taken to the answer;
    `dropped`: frames a free-running device delivered since the last answer that nobody took."""

    jpeg: bytes
    age: float
    dropped: int = 0


class Failed(msgspec.Struct, tag="failed", frozen=True):
    """The request could not be carried out; `gl`: because OpenGL could not start."""

    reason: str
    gl: bool = False


ToChild: TypeAlias = Open | Read
FromChild: TypeAlias = Opened | Frame | Failed
_encoder = msgspec.msgpack.Encoder()


class GLUnavailable(OSError):
    """What a source raises when the OpenGL backend it was given cannot start."""


def encode(message: ToChild | FromChild) -> bytes:
    """`message` as one frame."""
    return frames.pack(_encoder.encode(message), MAX_FRAME)


@dataclass(frozen=True)
class Recipe:
    """How to open a source in a capture process. `factory` ("module:callable") is called with
    `params` and `blob` and returns a `FrameSource` (`sources.py`), which may also have a
    `feed(bytes)` method; `feed` (in the server, before each frame) returns what it is fed, or
    raises `OSError` when there is nothing to draw any more; `gl`: it renders with OpenGL, so a
    backend that works here is looked for."""

    factory: str
    params: Mapping[str, Any]
    blob: bytes = b""
    feed: Callable[[], bytes] | None = field(default=None, compare=False)
    gl: bool = False


def named_recipe(source: str, width: int, height: int, fps: int) -> Recipe:
    """The recipe of a source a camera's `source` names (`sources.open_source`)."""
    params = {"source": source, "width": width, "height": height, "fps": fps}
    return Recipe("arena.sensors.sources:open_source", params)


# -- the server's side ---------------------------------------------------------------------------

#: The backend found to work (`MUJOCO_GL`'s value), once one has.
_working_gl: str | None = None


def gl_candidates() -> list[str]:
    """The OpenGL backends to try for MuJoCo: the one found to work, else `MUJOCO_GL`'s, then
    the headless ones (and GLFW where there is a display)."""
    if _working_gl is not None:
        return [_working_gl]
    found = [os.environ.get("MUJOCO_GL", "").strip().lower()]
    found += list(GL_BACKENDS) + (["glfw"] if os.environ.get("DISPLAY") else [])
    return [name for index, name in enumerate(found) if name and name not in found[:index]]


class CaptureProcess:
    """One capture process with its source open."""

    #: How the child is started: this interpreter, this module.
    command: Sequence[str] = (sys.executable, "-m", "arena.sensors.capture")

    def __init__(self, child: Child, recipe: Recipe) -> None:
        self.child = child
        self.recipe = recipe
        #: Whether the server keeps the rate (`Opened.paced`).
        self.paced = True

    @classmethod
    async def open(cls, recipe: Recipe) -> CaptureProcess:
        """Start a child and open `recipe`'s source in it; `OSError` with the reason if it
        cannot be (for OpenGL, each backend tried and why it failed)."""
        global _working_gl
        if not recipe.gl:
            return await cls._start(recipe, {})
        reasons = []
        for backend in gl_candidates():
            try:
                child = await cls._start(recipe, {"MUJOCO_GL": backend, "PYOPENGL_PLATFORM": None})
            except GLUnavailable as exc:
                reasons.append(f"{backend}: {exc}")
                continue
            _working_gl = backend
            return child
        raise OSError(
            "MuJoCo cannot render here (" + "; ".join(reasons) + "): install Debian's "
            "libosmesa6 or a GPU's EGL, or set MUJOCO_GL to a backend this machine has"
        )

    @classmethod
    async def _start(cls, recipe: Recipe, env: Mapping[str, str | None]) -> CaptureProcess:
        capture = cls(await Child.start(cls.command, "the capture process", env), recipe)
        try:
            opening = Open(recipe.factory, dict(recipe.params), recipe.blob)
            answer = await capture._ask(opening, OPEN_TIMEOUT)
            if isinstance(answer, Failed):
                raise (GLUnavailable if answer.gl else OSError)(answer.reason)
            if not isinstance(answer, Opened):
                raise OSError("the capture process answered its opening with a frame")
            capture.paced = answer.paced
        except BaseException:
            await capture.close()
            raise
        return capture

    @property
    def pid(self) -> int:
        """The child's process id."""
        return self.child.pid

    async def read(self) -> Frame:
        """The next frame; `OSError` when the source fails, and when the child dies or takes
        longer than `READ_TIMEOUT` (then it is killed: the caller opens another)."""
        feed = self.recipe.feed() if self.recipe.feed is not None else b""
        answer = await self._ask(Read(feed), READ_TIMEOUT)
        if isinstance(answer, Failed):
            raise OSError(answer.reason)
        if not isinstance(answer, Frame):
            raise OSError("the capture process answered a read with no frame")
        return answer

    async def _ask(self, request: ToChild, timeout: float) -> FromChild:
        try:
            with trio.fail_after(timeout):
                await self.child.send(encode(request))
                body = await self.child.receive(MAX_FRAME)
            answer: FromChild = msgspec.msgpack.decode(body, type=FromChild)
        except trio.TooSlowError:
            self.child.process.kill()
            raise OSError(
                f"the capture process gave no answer in {timeout:g} s (stuck in its source?): "
                "it was killed"
            ) from None
        except (trio.BrokenResourceError, trio.ClosedResourceError):
            raise OSError(await self.child.gone()) from None
        except (FrameError, msgspec.DecodeError) as exc:
            raise OSError(f"the capture process sent a bad frame: {exc}") from None
        return answer

    async def close(self) -> None:
        """Kill the child at once and reap it."""
        await self.child.close()


# -- the child -----------------------------------------------------------------------------------


class _Latest:
    """A free-running source (a device at its own rate) read by a thread of its own: a read
    takes the newest frame the thread has not yet handed out, waiting for one if need be."""

    def __init__(self, source: Any) -> None:
        self._source = source
        self._ready = threading.Condition()
        self._frame: tuple[bytes, float] | None = None
        self._error: OSError | None = None
        self.dropped = 0
        threading.Thread(target=self._run, name="device", daemon=True).start()

    def _run(self) -> None:
        while True:
            try:
                jpeg = self._source.read()
            except OSError as exc:
                with self._ready:
                    self._error = exc
                    self._ready.notify()
                return
            with self._ready:
                self.dropped += self._frame is not None
                self._frame = (jpeg, time.perf_counter())
                self._ready.notify()

    def take(self) -> tuple[bytes, float, int]:
        with self._ready:
            while self._frame is None and self._error is None:
                self._ready.wait()
            if self._frame is None:
                assert self._error is not None
                raise self._error
            (jpeg, at), self._frame = self._frame, None
            dropped, self.dropped = self.dropped, 0
        return jpeg, at, dropped


def _die_with_parent() -> None:
    """End this process soon after the server's end, even while its main thread is stuck in a
    source (one that lets go of the interpreter's lock, as reading a device does). Not Linux's
    parent-death signal: that follows the thread that started the child, and trio starts
    children from worker threads that end when idle."""
    parent = os.getppid()

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(1.0)
        os._exit(0)

    threading.Thread(target=watch, name="parent", daemon=True).start()


def _make(request: Open) -> Any:
    module, _, name = request.factory.partition(":")
    factory = getattr(importlib.import_module(module), name)
    kwargs = dict(request.params)
    if request.blob:
        kwargs["blob"] = request.blob
    return factory(**kwargs)


def _answer(request: ToChild, state: dict[str, Any]) -> FromChild:
    """The child's answer to one request; `state` holds its open source."""
    if isinstance(request, Open):
        try:
            source = _make(request)
        except GLUnavailable as exc:
            return Failed(str(exc), gl=True)
        except Exception as exc:  # whatever a source's library raises: the camera's error
            return Failed(str(exc) or type(exc).__name__)
        paced = bool(getattr(source, "paced", True))
        state["source"] = source
        state["latest"] = None if paced else _Latest(source)
        return Opened(paced)
    source = state.get("source")
    if source is None:
        return Failed("no source is open")
    try:
        if request.feed:
            source.feed(request.feed)
        if state["latest"] is not None:
            jpeg, at, dropped = state["latest"].take()
            return Frame(jpeg, time.perf_counter() - at, dropped)
        jpeg = source.read()
        exposed = getattr(source, "exposed", None)
        return Frame(jpeg, 0.0 if exposed is None else time.perf_counter() - exposed)
    except Exception as exc:
        return Failed(str(exc) or type(exc).__name__)


def _read_exactly(stream: IO[bytes], count: int) -> bytes | None:
    data = stream.read(count)
    return data if len(data) == count else None


def main() -> None:
    """Serve one source's frames over stdin and stdout until stdin ends."""
    # A terminal's Ctrl-C reaches the whole process group: the server stops its children.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _die_with_parent()
    stdin, stdout = sys.stdin.buffer, sys.stdout.buffer
    sys.stdout = sys.stderr  # stdout carries frames only: a library's print goes to the log
    state: dict[str, Any] = {}
    while (header := _read_exactly(stdin, HEADER.size)) is not None:
        body = _read_exactly(stdin, frames.frame_length(header, MAX_FRAME))
        if body is None:
            break
        answer = _answer(msgspec.msgpack.decode(body, type=ToChild), state)
        stdout.write(encode(answer))
        stdout.flush()
    source = state.get("source")
    if source is not None:
        source.close()


if __name__ == "__main__":
    # Run as the module's real name, so a source's `GLUnavailable` is the one caught here.
    from arena.sensors import capture

    capture.main()
