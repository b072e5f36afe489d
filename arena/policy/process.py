"""A policy worker as seen from trio: start it, load the policy, ask for chunks, stop it.

The worker is `python -m arena.policy.worker`, a child process started with
`trio.lowlevel.open_process` and pipes for stdin and stdout (its stderr is the parent's, for
LeRobot's own logging). One request is in flight at a time. `close` ends it: its stdin closed
and the process killed. A worker whose parent dies sees its stdin end and exits by itself.
"""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import ClassVar

import trio

import arena
from arena.policy.wire import (
    HEADER,
    Chunk,
    Failed,
    FrameError,
    FromWorker,
    Load,
    Loaded,
    Observe,
    decode_from_worker,
    encode,
    frame_length,
)
from arena.protocol.errors import ArenaError, ErrorCode

#: Seconds a worker has to start, import torch and LeRobot and load the weights (the master's
#: default `load_timeout`).
LOAD_TIMEOUT = 180.0
#: Workers one process runs at most (each holds a policy's weights and torch: hundreds of MB).
MAX_WORKERS = 4
#: How a worker is started: this interpreter, the worker module.
WORKER = (sys.executable, "-m", "arena.policy.worker")
#: Seconds to wait for a killed worker to be reaped.
STOP_WAIT = 5.0


class WorkerError(Exception):
    """The worker refused a request (the message is its reason) or is gone."""


class WorkerGone(WorkerError):
    """The worker has exited (or closed its pipes): no answer will come."""


class PolicyProcess:
    """One worker process and the policy it holds."""

    #: The workers started and not yet closed, all of this process's (bounded by MAX_WORKERS).
    live: ClassVar[set[PolicyProcess]] = set()

    def __init__(self, process: trio.Process) -> None:
        self.process = process
        assert process.stdin is not None and process.stdout is not None
        self._stdin = process.stdin
        self._stdout = process.stdout
        self._buffer = bytearray()
        self._lock = trio.Lock()
        self._broken = False

    @classmethod
    async def start(cls, command: Sequence[str] = WORKER) -> PolicyProcess:
        """Start a worker (it imports nothing heavy until asked to load); OVERLOADED when
        `MAX_WORKERS` run already. `command`: the worker's (tests start stand-ins)."""
        if len(cls.live) >= MAX_WORKERS:
            raise ArenaError(
                ErrorCode.OVERLOADED,
                f"{len(cls.live)} policies run or load already (at most {MAX_WORKERS}): "
                "detach one first.",
            )
        env = dict(os.environ)
        # The worker imports the same `arena` as this process, wherever it was found.
        root = str(Path(arena.__file__).resolve().parent.parent)
        env["PYTHONPATH"] = os.pathsep.join(p for p in (root, env.get("PYTHONPATH")) if p)
        process = await trio.lowlevel.open_process(
            list(command),
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            env=env,
        )
        worker = cls(process)
        cls.live.add(worker)
        return worker

    @property
    def pid(self) -> int:
        """The worker's process id."""
        return int(self.process.pid)

    @property
    def exited(self) -> bool:
        """Whether the worker has ended."""
        return self.process.poll() is not None

    async def load(self, path: Path) -> Loaded:
        """Load the policy in `path`; `WorkerError` with the worker's reason if it cannot
        (the caller bounds the time it takes: `PolicyMaster.prepare`)."""
        answer = await self._ask(Load(str(path)))
        if not isinstance(answer, Loaded):
            raise WorkerError(answer.reason if isinstance(answer, Failed) else "unexpected answer")
        return answer

    async def act(self, observation: Observe) -> Chunk:
        """The action chunk for `observation`."""
        answer = await self._ask(observation)
        if not isinstance(answer, Chunk):
            raise WorkerError(answer.reason if isinstance(answer, Failed) else "unexpected answer")
        return answer

    async def _ask(self, request: Load | Observe) -> FromWorker:
        async with self._lock:
            if self._broken:
                raise WorkerGone("an earlier request to the worker was abandoned half-way")
            self._broken = True  # until the answer is read whole: a cancelled read desyncs
            try:
                await self._stdin.send_all(encode(request))
                header = await self._read(HEADER.size)
                answer = decode_from_worker(await self._read(frame_length(header)))
            except (trio.BrokenResourceError, trio.ClosedResourceError) as exc:
                raise WorkerGone(await self._gone()) from exc
            except FrameError as exc:
                raise WorkerGone(f"the worker sent a bad frame: {exc}") from exc
            self._broken = False
            return answer

    async def _read(self, count: int) -> bytes:
        while len(self._buffer) < count:
            data = await self._stdout.receive_some(max(65536, count - len(self._buffer)))
            if not data:
                raise WorkerGone(await self._gone())
            self._buffer += data
        taken = bytes(self._buffer[:count])
        del self._buffer[:count]
        return taken

    async def _gone(self) -> str:
        """Why the worker's pipes ended: its exit code, once it is reaped (an exit closes the
        pipes a moment before the process is reaped)."""
        with trio.move_on_after(STOP_WAIT):
            await self.process.wait()
        code = self.process.poll()
        return "the worker has exited" + ("" if code is None else f" (code {code})")

    async def close(self) -> None:
        """Stop the worker at once: it holds nothing that needs a graceful end, and a worker in
        the middle of an inference would not see its stdin close until the inference ends."""
        PolicyProcess.live.discard(self)
        with trio.CancelScope(shield=True):
            with contextlib.suppress(trio.BrokenResourceError, trio.ClosedResourceError):
                await self._stdin.aclose()
            if self.process.poll() is None:
                self.process.kill()
            with trio.move_on_after(STOP_WAIT):
                await self.process.wait()
            await self._stdout.aclose()
