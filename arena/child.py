"""The server's helper processes: a policy's worker, a camera's capture process. Each is a child
started with pipes on its stdin and stdout, which carry length-prefixed frames
(`arena.protocol.frames`), one request and its answer at a time.

Native code that can block while holding the interpreter's lock (inference, rendering, a
device's driver) runs in such a child, so the server's event loop and its e-stop answer
whatever the child does; a child that hangs is killed (`Child.close`), never waited for.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
from collections.abc import Mapping, Sequence
from pathlib import Path

import trio

from arena.protocol.frames import HEADER, frame_length

#: Seconds to wait for a killed child to be reaped.
STOP_WAIT = 5.0


class Child:
    """One child process and its pipes, seen from trio."""

    def __init__(self, process: trio.Process, name: str) -> None:
        self.process = process
        self.name = name  # "the worker", "the capture process": what its errors call it
        assert process.stdin is not None and process.stdout is not None
        self._stdin = process.stdin
        self._stdout = process.stdout
        self._buffer = bytearray()

    @classmethod
    async def start(
        cls, command: Sequence[str], name: str, env: Mapping[str, str | None] | None = None
    ) -> Child:
        """Start `command` with pipes for stdin and stdout (stderr is the server's, its log);
        it imports the same `arena` as this process. `env`: variables to set (None: unset)."""
        environment = dict(os.environ)
        root = str(Path(__file__).resolve().parent.parent)  # where `arena` was found
        environment["PYTHONPATH"] = os.pathsep.join(
            p for p in (root, environment.get("PYTHONPATH")) if p
        )
        for variable, value in (env or {}).items():
            if value is None:
                environment.pop(variable, None)
            else:
                environment[variable] = value
        process = await trio.lowlevel.open_process(
            list(command), stdin=subprocess.PIPE, stdout=subprocess.PIPE, env=environment
        )
        return cls(process, name)

    @property
    def pid(self) -> int:
        """The child's process id."""
        return int(self.process.pid)

    async def send(self, frame: bytes) -> None:
        """Write `frame` whole; `trio.BrokenResourceError` once the child is gone."""
        await self._stdin.send_all(frame)

    async def receive(self, limit: int) -> bytes:
        """The body of the next frame; `trio.BrokenResourceError` when the pipe ends first,
        `FrameError` past `limit`."""
        return await self._exactly(frame_length(await self._exactly(HEADER.size), limit))

    async def _exactly(self, count: int) -> bytes:
        while len(self._buffer) < count:
            data = await self._stdout.receive_some(max(65536, count - len(self._buffer)))
            if not data:
                raise trio.BrokenResourceError(f"{self.name} closed its pipe")
            self._buffer += data
        taken = bytes(self._buffer[:count])
        del self._buffer[:count]
        return taken

    async def gone(self) -> str:
        """Why the pipes ended, in a sentence: how the child exited, once it is reaped (an exit
        closes the pipes a moment before the process is reaped)."""
        with trio.move_on_after(STOP_WAIT):
            await self.process.wait()
        code = self.process.poll()
        if code is None:
            return f"{self.name} closed its pipes"
        if code < 0:
            with contextlib.suppress(ValueError):
                return f"{self.name} died ({signal.Signals(-code).name})"
        return f"{self.name} has exited (code {code})"

    async def close(self) -> None:
        """Kill the child at once (one busy in native code would not see its stdin close) and
        reap it."""
        with trio.CancelScope(shield=True):
            with contextlib.suppress(trio.BrokenResourceError, trio.ClosedResourceError):
                await self._stdin.aclose()
            if self.process.poll() is None:
                self.process.kill()
            with trio.move_on_after(STOP_WAIT):
                await self.process.wait()
            await self._stdout.aclose()
