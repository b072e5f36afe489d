"""`arena serve` (or a program that serves) as a real process for tests: started, its URL
read from its log, stopped."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import threading
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path


@dataclass
class ServeProcess:
    """A running `arena serve`: its process, its URL, and its log so far (read by a thread, so
    the pipe never fills)."""

    process: subprocess.Popen[str]
    url: str = ""
    lines: list[str] = field(default_factory=list)
    listening: threading.Event = field(default_factory=threading.Event)
    ended: threading.Event = field(default_factory=threading.Event)

    @property
    def log(self) -> str:
        return "".join(self.lines)

    def read(self) -> None:
        assert self.process.stderr is not None
        for line in self.process.stderr:
            self.lines.append(line)
            found = re.search(r"listening on (http://\S+)", line)
            if found and not self.url:
                self.url = found.group(1)
                self.listening.set()
        self.ended.set()
        self.listening.set()  # a process that ended never listens: wake the waiter


@contextmanager
def serving(
    argv: Sequence[str],
    *,
    cwd: Path,
    env: dict[str, str] | None = None,
    python: str = sys.executable,
    timeout: float = 60.0,
    program: Sequence[str] = ("-m", "arena", "serve"),
) -> Iterator[ServeProcess]:
    """Run `python -m arena serve ARGV` (or `python PROGRAM ARGV`: a script that serves as
    `run_server` does, logging to stderr) in `cwd` with the environment `env` (default: this
    process's) until the block ends (then SIGKILL if still running). Yields once it listens;
    raises with its log if it ends first."""
    environment = {**(os.environ if env is None else env), "LOG_LEVEL": "INFO"}
    process = subprocess.Popen(
        [python, *program, *argv],
        stderr=subprocess.PIPE,
        stdout=subprocess.DEVNULL,
        text=True,
        cwd=cwd,
        env=environment,
    )
    served = ServeProcess(process)
    reader = threading.Thread(target=served.read, daemon=True)
    reader.start()
    try:
        served.listening.wait(timeout)
        if not served.url:
            raise AssertionError(f"arena serve did not listen:\n{served.log}")
        yield served
    finally:
        if process.poll() is None:
            process.send_signal(signal.SIGKILL)
        process.wait(timeout=30)
        reader.join(timeout=30)
