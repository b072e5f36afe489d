"""The sequence a WebSocket master asked for, played under that master's ownership."""

from __future__ import annotations

import trio

from arena.drivers.sequence_master import SequenceMaster
from arena.robot.links import MasterLink


class SequencePlayer:
    """Plays one sequence at a time for a master connection; a new one, an e-stop or a
    release stops the one playing. `releasing`: the master said `release` (its link ends
    without a word from the robot)."""

    def __init__(self) -> None:
        self.scope: trio.CancelScope | None = None
        self.releasing = False

    def stop(self) -> None:
        """Stop the sequence playing, if any."""
        if self.scope is not None:
            self.scope.cancel()
            self.scope = None

    async def play(self, link: MasterLink, master: SequenceMaster) -> None:
        """Play `master`'s sequences on `link` until they end or `stop`."""
        with trio.CancelScope() as scope:
            self.scope = scope
            await master.run(link)
