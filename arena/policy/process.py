"""A policy worker as seen from trio: start it, load the policy, ask for chunks, stop it.

The worker is `python -m arena.policy.worker`, a child process started with
`trio.lowlevel.open_process` and pipes for stdin and stdout (its stderr is the parent's, for
LeRobot's own logging). One request is in flight at a time. `close` ends it: its stdin closed
and the process killed. A worker whose parent dies sees its stdin end and exits by itself.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from pathlib import Path
from typing import ClassVar

import trio

from arena.child import Child
from arena.policy.wire import (
    MAX_FRAME,
    Chunk,
    Failed,
    FrameError,
    FromWorker,
    Load,
    Loaded,
    Observe,
    decode_from_worker,
    encode,
)
from arena.protocol.errors import ArenaError, ErrorCode

#: Seconds a worker has to start, import torch and LeRobot and load the weights (the master's
#: default `load_timeout`).
LOAD_TIMEOUT = 180.0
#: Workers one process runs at most (each holds a policy's weights and torch: hundreds of MB).
MAX_WORKERS = 4
#: How a worker is started in Arena's own Python: this interpreter, the worker module.
WORKER = (sys.executable, "-m", "arena.policy.worker")
#: ...and in a Python of the user's (`arena serve --policy-python`), one with LeRobot, torch and
#: msgspec but no Arena: isolated (`-I`: no PYTHONPATH, no user site), Arena's source found by
#: its folder alone (the argument after the code).
BOOT = "import sys; sys.path.insert(0, sys.argv[1]); from arena.policy.worker import main; main()"
ROOT = Path(__file__).resolve().parent.parent.parent


def worker_command(python: str | None) -> tuple[str, ...]:
    """The command that starts a worker in `python` (None: Arena's own)."""
    return WORKER if python is None else (python, "-I", "-c", BOOT, str(ROOT))


class WorkerError(Exception):
    """The worker refused a request (the message is its reason) or is gone."""


class WorkerGone(WorkerError):
    """The worker has exited (or closed its pipes): no answer will come."""


class PolicyProcess:
    """One worker process and the policy it holds."""

    #: The workers started and not yet closed, all of this process's (bounded by MAX_WORKERS).
    live: ClassVar[set[PolicyProcess]] = set()

    def __init__(self, child: Child) -> None:
        self.child = child
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
        child = await Child.start(command, "the worker")
        worker = cls(child)
        cls.live.add(worker)
        return worker

    @property
    def pid(self) -> int:
        """The worker's process id."""
        return self.child.pid

    @property
    def exited(self) -> bool:
        """Whether the worker has ended."""
        return self.child.process.poll() is not None

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
                await self.child.send(encode(request))
                answer = decode_from_worker(await self.child.receive(MAX_FRAME))
            except (trio.BrokenResourceError, trio.ClosedResourceError) as exc:
                raise WorkerGone(await self.child.gone()) from exc
            except FrameError as exc:
                raise WorkerGone(f"the worker sent a bad frame: {exc}") from exc
            self._broken = False
            return answer

    async def close(self) -> None:
        """Stop the worker at once: it holds nothing that needs a graceful end, and a worker in
        the middle of an inference would not see its stdin close until the inference ends."""
        PolicyProcess.live.discard(self)
        await self.child.close()
