"""`arena replay`: play a recording into a running server as a WebSocket master.

A replay that ran to its end releases the robot (it holds where it is, `idle`); one that was
stopped (e-stopped, taken over, refused) or failed just goes, and the server's loss policy
applies to what is left of it.
"""

from __future__ import annotations

import json
import sys
from typing import TextIO

import trio
from trio_websocket import ConnectionClosed, open_websocket_url

from arena.protocol.errors import ArenaError, ErrorCode
from arena.protocol.messages import CommandData, CommandMessage, JointValue, ReleaseMessage, encode
from arena.recording.replay import TimedCommand

#: Seconds to wait for the answer to the release at the end.
RELEASE_TIMEOUT = 5.0
#: The server's refusals of this master (as it connects; a token expired): raised.
_REFUSALS = frozenset({"MASTER_ACTIVE", "UNKNOWN_ROBOT", "UNAUTHORIZED", "FORBIDDEN"})
#: The same refusals as the close codes the server ends the connection with.
_CLOSE_CODES = {
    4409: ErrorCode.MASTER_ACTIVE,
    4404: ErrorCode.UNKNOWN_ROBOT,
    4401: ErrorCode.UNAUTHORIZED,
    4403: ErrorCode.FORBIDDEN,
}


def _message(command: TimedCommand, speed: float) -> str:
    """The recorded command as the master's `command` (the protocol's struct), its duration
    (ms) scaled to `speed`."""
    joints = [JointValue(g.name, g.value, g.speed or None) for g in command.command.joints]
    duration = command.command.duration
    data = CommandData(
        joints=joints,
        duration=None if duration is None else duration * 1000.0 / speed,
        metadata={"source": "arena replay"},
    )
    return encode(CommandMessage(data=data))


def _progress(out: TextIO, done: int, total: int, refused: int) -> None:
    width = 30
    filled = width * done // total
    out.write(f"\r[{'#' * filled}{'.' * (width - filled)}] {done}/{total} refused {refused}")
    out.flush()


async def replay_to_server(
    url: str,
    commands: list[TimedCommand],
    *,
    speed: float = 1.0,
    loop: bool = False,
    out: TextIO | None = None,
) -> tuple[int, int]:
    """Send `commands` with their timing to a master WebSocket; returns (sent, refused).
    Progress goes to `out` (default: the `sys.stderr` of the moment of the call).

    Raises `ArenaError` (`NOT_OWNER`) if the release at the end was not answered `released`,
    and the server's refusal of this master (MASTER_ACTIVE, UNKNOWN_ROBOT, UNAUTHORIZED,
    FORBIDDEN: as it connects, or a token that expires).
    """
    if not 0.01 <= speed <= 1000:
        raise ArenaError(ErrorCode.INVALID_VALUE, "--speed must be between 0.01 and 1000.")
    out = sys.stderr if out is None else out
    sent = refused = 0
    released: dict[str, object] | None = None
    releasing = False
    refusal: ArenaError | None = None  # the server refused this master
    ended = False  # the server detached this master (taken over, lost): said, not an error
    async with open_websocket_url(url) as ws:
        stopped = trio.Event()
        answered = trio.Event()  # the release's answer (or the end of the link)

        async def read_answers() -> None:
            nonlocal refused, released, refusal, ended
            try:
                while True:
                    answer = json.loads(await ws.get_message())
                    kind = answer.get("type")
                    ended = ended or kind == "detached"  # (its close code is no refusal)
                    if kind == "released":
                        released = answer.get("data") or {}
                        answered.set()
                    elif kind == "error" and releasing:
                        out.write(f"\nserver: {answer.get('data', {}).get('message')}\n")
                        answered.set()
                    elif kind == "ack" and answer["data"]["status"] == "refused":
                        refused += 1
                        if answer["data"]["code"] in ("ESTOPPED", "NOT_OWNER"):
                            stopped.set()
                    elif kind == "error" and answer.get("data", {}).get("code") in _REFUSALS:
                        data = answer["data"]
                        refusal = ArenaError(ErrorCode(data["code"]), data["message"])
                        stopped.set()
                    elif kind in ("detached", "error") and answer.get("data", {}).get("code") in (
                        "TAKEN_OVER",
                        "MASTER_LOST",
                    ):
                        out.write(f"\nserver: {answer['data']['message']}\n")
                        stopped.set()
            except ConnectionClosed as closed:
                reason = closed.reason
                code = None if reason is None else _CLOSE_CODES.get(reason.code)
                # A refusal whose close came before its message (a takeover closes 4409 too,
                # after its `detached`: that is an end, not a refusal).
                if refusal is None and not ended and code is not None:
                    assert reason is not None
                    refusal = ArenaError(code, reason.reason or str(code))
                stopped.set()
                answered.set()

        async with trio.open_nursery() as nursery:
            nursery.start_soon(read_answers)
            while not stopped.is_set():
                start = trio.current_time()
                for index, command in enumerate(commands):
                    await trio.sleep_until(start + command.at / speed)
                    if stopped.is_set():
                        break
                    try:
                        await ws.send_message(_message(command, speed))
                    except ConnectionClosed:  # the server closed it: its reader says why
                        stopped.set()
                        break
                    sent += 1
                    _progress(out, index + 1, len(commands), refused)
                if not loop:
                    break
            releasing = not stopped.is_set()
            if releasing:  # played to the end: hand the robot back
                await ws.send_message(encode(ReleaseMessage()))
                with trio.move_on_after(RELEASE_TIMEOUT):
                    await answered.wait()
            else:
                await trio.sleep(0.2)  # let the last answers arrive
            nursery.cancel_scope.cancel()
    out.write("\n")
    if refusal is not None:
        raise refusal
    if releasing and released is None:
        raise ArenaError(ErrorCode.NOT_OWNER, "The server did not answer the release.")
    return sent, refused
