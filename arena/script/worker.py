"""A script's worker: `python -m arena.script.worker FILE` runs FILE as `__main__`, its calls
of `arena.script` going as requests over the pipe on its stdin and stdout (`wire.py`).

The pipe is taken off fds 0 and 1 first: the script's `input()` reads nothing, a stray write
to fd 1 lands on stderr, and `print` and the script's stderr go as lines to the master, which
bounds and logs them. How the script ended goes last: `finished`, or `failed` with the
exception and the script's line. The worker exits when its pipe ends (the master gone).
"""

from __future__ import annotations

import io
import os
import runpy
import sys
import traceback
from pathlib import Path
from types import TracebackType

from arena.script.api import Channel, connect
from arena.script.wire import MAX_LINE, Failed, Finished, FrameError, Line

#: The longest traceback sent (characters; its end is kept).
MAX_TRACEBACK = 4000


class LineWriter(io.TextIOBase):
    """A text stream that sends each whole line it is given as a `line` message."""

    def __init__(self, channel: Channel, stream: str) -> None:
        super().__init__()
        self.channel = channel
        self.stream = stream
        self.pending = ""

    def writable(self) -> bool:
        return True

    def write(self, text: str) -> int:
        self.pending += text
        while "\n" in self.pending:
            line, self.pending = self.pending.split("\n", 1)
            self._send(line)
        while len(self.pending) > MAX_LINE:  # a line with no end yet: sent in pieces
            self._send(self.pending[:MAX_LINE])
            self.pending = self.pending[MAX_LINE:]
        return len(text)

    def flush(self) -> None:
        if self.pending:
            self._send(self.pending)
            self.pending = ""

    def _send(self, line: str) -> None:
        if len(line) > MAX_LINE:
            line = line[:MAX_LINE] + " [cut]"
        self.channel.tell(Line(line, self.stream))


def where(script: Path, tb: TracebackType | None) -> tuple[str, int]:
    """The script's file and the line of its deepest frame in `tb` (0: none, a syntax error
    carries its own)."""
    line = 0
    for frame, number in traceback.walk_tb(tb):
        if Path(frame.f_code.co_filename).resolve() == script:
            line = number
    return str(script), line


def failure(script: Path, exc: BaseException) -> Failed:
    """How `exc` ended the script."""
    file, line = where(script, exc.__traceback__)
    if isinstance(exc, SyntaxError) and exc.lineno is not None:
        line = exc.lineno
    text = "".join(traceback.format_exception(exc))[-MAX_TRACEBACK:]
    return Failed(type(exc).__name__, str(exc)[:MAX_LINE], file, line, text)


def main() -> None:
    """Run the script named by the first argument."""
    script = Path(sys.argv[1]).resolve()
    reader = os.fdopen(os.dup(0), "rb", buffering=0)
    writer = os.fdopen(os.dup(1), "wb", buffering=0)
    null = os.open(os.devnull, os.O_RDONLY)
    os.dup2(null, 0)
    os.dup2(2, 1)
    channel = Channel(reader, writer)
    connect(channel)
    out, err = LineWriter(channel, "stdout"), LineWriter(channel, "stderr")
    sys.stdout, sys.stderr = out, err
    sys.argv = [str(script)]
    sys.path.insert(0, str(script.parent))
    end: Finished | Failed = Finished()
    try:
        runpy.run_path(str(script), run_name="__main__")
    except SystemExit as exc:
        if exc.code not in (None, 0):
            end = failure(script, exc)
    except FrameError:
        os._exit(0)  # the master is gone: nobody to tell
    except BaseException as exc:  # the script's own error, whatever it is: reported
        end = failure(script, exc)
    try:
        out.flush()
        err.flush()
        channel.tell(end)
    except (OSError, FrameError):
        pass
    os._exit(0)  # (threads the script left running do not keep the worker alive)


if __name__ == "__main__":
    main()
