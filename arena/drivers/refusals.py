"""What a master driver keeps of the commands the robot refused: a count, and the newest few."""

from __future__ import annotations

import collections
from collections.abc import Iterator

from arena.protocol.errors import ErrorCode

#: Refusals kept for inspection; older ones are only counted.
KEPT = 100


class Refusals:
    """The newest `KEPT` refusals (code, sentence) and how many there were in all. A master
    that runs for days (a looping sequence refused by a rate limit) keeps bounded memory."""

    def __init__(self, kept: int = KEPT) -> None:
        self._newest: collections.deque[tuple[ErrorCode | None, str]] = collections.deque(
            maxlen=kept
        )
        self.total = 0

    def append(self, refusal: tuple[ErrorCode | None, str]) -> None:
        """One more refusal."""
        self._newest.append(refusal)
        self.total += 1

    def __len__(self) -> int:
        return len(self._newest)

    def __iter__(self) -> Iterator[tuple[ErrorCode | None, str]]:
        return iter(self._newest)

    def __getitem__(self, index: int) -> tuple[ErrorCode | None, str]:
        return self._newest[index]
