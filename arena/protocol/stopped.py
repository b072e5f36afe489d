"""The `stopped` message to a master: the collision guard stopped a motion it had accepted from
this master, on the way the joints really take (specs/collision.md, "Stopped on the way").
Beside `messages` (at its size limit), in the same shape: `type`, `timestamp`, `data`."""

from __future__ import annotations

import msgspec


class StoppedData(msgspec.Struct, omit_defaults=True):
    """Why: the code (COLLISION), a sentence saying what would have met and where the arm
    holds, and the two things that would have met (`blocked`, as NO_PATH's)."""

    code: str
    message: str
    blocked: list[str] | None = None


class StoppedNotice(
    msgspec.Struct, tag_field="type", tag="stopped", omit_defaults=True, kw_only=True
):
    """To a master: its accepted motion was stopped on its way; the arm holds where it got to
    (a new command moves it again)."""

    timestamp: str | None = None
    data: StoppedData
