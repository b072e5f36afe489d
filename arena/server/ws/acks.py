"""A master's acknowledgments, encoded: a plain acceptance once per millisecond.

A burst of commands gets many plain acceptances within one millisecond (the timestamp's
resolution), all the same text: the app keeps the newest one encoded (one entry, for the
app's lifetime, shared by its masters), and the transport frames the same text object once.
"""

from __future__ import annotations

from arena.protocol import messages as wire
from arena.robot.motion import CommandResult
from arena.server import convert
from arena.server.ws.backpressure import Encoded, Outgoing


class AckCache:
    """Masters' acks; holds the last plain acceptance encoded (one entry)."""

    __slots__ = ("_accepted", "_stamp")

    def __init__(self) -> None:
        self._stamp = ""
        self._accepted = Encoded("ack", "")

    def ack(self, result: CommandResult) -> Outgoing:
        """The ack of a command; a plain acceptance is encoded once per millisecond."""
        if not result.accepted or result.clamped:
            return convert.ack(result)
        stamp = wire.now_iso()
        if stamp != self._stamp:
            message = wire.AckMessage(timestamp=stamp, data=wire.AckData("accepted"))
            self._stamp, self._accepted = stamp, Encoded("ack", wire.encode(message))
        return self._accepted
