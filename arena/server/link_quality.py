"""A master's link as the server sees it: the age of each stamped command, its round trip and
jitter, and the commands dropped for arriving too late (specs/remote-link.md).

Age. A master stamps a command with its own clock (`data.timestamp`, ms since the epoch). On
arrival, `arrival - stamp` is the one-way delay plus the offset between the two clocks; the
smallest such sample seen is the fastest trip plus that offset, so `sample - floor` is how much
later than the fastest trip this command came, whatever the offset (NTP's idea, one way). Half
the smallest round trip of the pings adds the fastest trip itself: `age = sample - floor +
min_rtt / 2`. The floor may creep up by `FLOOR_RISE` seconds a second of arrivals (clock drift,
a slower route), never more: a stall's backlog, which arrives all at once, cannot lift it. A
master whose commands are all stale for `RESYNC_AFTER` seconds while a ping's round trip says
the link is quick has had its clock set back: the floor starts over.

Round trip. The server pings each master every `link_ping_interval` (a WebSocket ping, which
every client answers by itself, browsers included: no change to the protocol), and times the
pong. Jitter is RFC 3550's estimate over the one-way transit of stamped commands, or, for a
master that stamps none, over the round trips.

All times are trio's clock (`wall_now` anchors it to the epoch once), so that a test on the
mock clock decides everything here.
"""

from __future__ import annotations

import math
import struct
import time
from collections import OrderedDict
from typing import Any

import trio

#: How fast the floor may rise: 10 ms a second of arrivals (a clock drifts by 0.1 ms a second
#: at worst; a route 300 ms slower is learnt in half a minute).
FLOOR_RISE = 0.01
#: A gap in the arrivals counts at most this long toward the rise (a long stall lifts nothing).
RISE_GAP_CAP = 1.0
#: Only-stale commands for this long with a quick round trip: the master's clock moved.
RESYNC_AFTER = 1.0
#: Pings awaiting their pong, at most (older ones are forgotten: bounded memory).
PINGS_KEPT = 8
#: RFC 3550's gain for the jitter estimate.
JITTER_GAIN = 1 / 16
#: The qualities, as `/metrics` numbers them.
QUALITY_LEVELS = {"unknown": 0, "good": 1, "fair": 2, "poor": 3}
#: Recent stale drops make the link "poor" for this long.
STALE_RECENT = 5.0


class LinkQuality:
    """One master connection's link. `max_age` None (or 0): stale commands are not dropped."""

    def __init__(self, master_id: str, max_age: float | None, ping_interval: float) -> None:
        self.master_id = master_id
        self.max_age = max_age or None
        self.ping_interval = ping_interval
        self._epoch = time.time() - trio.current_time()
        self._floor: float | None = None
        self._last_arrival = -math.inf
        self._last_transit: float | None = None
        self._stale_since: float | None = None
        self._last_stamp = -math.inf
        self._pings: OrderedDict[int, float] = OrderedDict()
        self._next_ping = 0
        self.started = trio.current_time()
        #: Pinged by the server (a socket carried from another node of a fleet is not).
        self.pinging = False
        self.rtt: float | None = None  # the last round trip
        self.rtt_min: float | None = None
        self.jitter = 0.0
        self._last_rtt: float | None = None
        self.last_pong_at: float | None = None
        self.stamped = 0  # commands with a timestamp
        self.stale = 0  # ...dropped for arriving too late
        self.last_stale_at: float | None = None
        self.last_age: float | None = None

    def wall_now(self) -> float:
        """Seconds since the epoch, on trio's clock (anchored once: steady, and virtual under
        the mock clock)."""
        return self._epoch + trio.current_time()

    # -- commands --------------------------------------------------------------------------------

    def age(self, stamp_ms: float) -> float | None:
        """The estimated age in seconds, now, of a message the master stamped `stamp_ms` (None:
        not a usable stamp). Updates the clock estimate."""
        if not math.isfinite(stamp_ms):
            return None
        now = trio.current_time()
        sample = self.wall_now() - stamp_ms / 1000.0
        if self._floor is None:
            self._floor = sample
        else:
            gap = min(max(now - self._last_arrival, 0.0), RISE_GAP_CAP)
            self._floor = min(sample, self._floor + FLOOR_RISE * gap)
        self._last_arrival = now
        if self._last_transit is not None:
            self.jitter += (abs(sample - self._last_transit) - self.jitter) * JITTER_GAIN
        self._last_transit = sample
        base = 0.0 if self.rtt_min is None else self.rtt_min / 2
        self.last_age = sample - self._floor + base
        return self.last_age

    def admit(self, stamp_ms: float | None) -> bool:
        """True if a command stamped `stamp_ms` is fresh enough to execute; a stale one is
        counted. One unstamped, or stamped no later than the one before, is admitted."""
        if stamp_ms is None or not math.isfinite(stamp_ms) or stamp_ms <= self._last_stamp:
            # Not later than the one before: not a clock reading (the seed's example stamp,
            # copied into every command): taken as unstamped.
            return True
        self._last_stamp = stamp_ms
        age = self.age(stamp_ms)
        if age is None:
            return True
        self.stamped += 1
        if self.max_age is None or age <= self.max_age:
            self._stale_since = None
            return True
        now = trio.current_time()
        if self._stale_since is None:
            self._stale_since = now
        elif self._clock_moved(now):
            self._floor = self.wall_now() - stamp_ms / 1000.0  # start over from this one
            self._stale_since = None
            return True
        self.stale += 1
        self.last_stale_at = now
        return False

    def _clock_moved(self, now: float) -> bool:
        """Only stale commands for a while, yet a pong since says the link is quick."""
        assert self._stale_since is not None and self.max_age is not None
        return (
            now - self._stale_since >= RESYNC_AFTER
            and self.last_pong_at is not None
            and self.last_pong_at > self._stale_since
            and self._last_rtt is not None
            and self._last_rtt / 2 <= self.max_age
        )

    # -- pings -----------------------------------------------------------------------------------

    def ping_payload(self) -> bytes:
        """The payload of the next ping (its number), noted as sent now."""
        self.pinging = True
        number = self._next_ping
        self._next_ping += 1
        self._pings[number] = trio.current_time()
        while len(self._pings) > PINGS_KEPT:
            self._pings.popitem(last=False)
        return struct.pack("!Q", number)

    def pong(self, payload: bytes) -> None:
        """A pong came: its ping's round trip (an unknown payload is ignored)."""
        if len(payload) != 8:
            return
        sent = self._pings.pop(struct.unpack("!Q", payload)[0], None)
        if sent is None:
            return
        now = trio.current_time()
        rtt = now - sent
        if not self.stamped and self._last_rtt is not None:
            self.jitter += (abs(rtt - self._last_rtt) - self.jitter) * JITTER_GAIN
        self._last_rtt = self.rtt = rtt
        self.rtt_min = rtt if self.rtt_min is None else min(self.rtt_min, rtt)
        self.last_pong_at = now

    # -- showing ---------------------------------------------------------------------------------

    def quality(self) -> str:
        """`unknown` (no pong yet), `good`, `fair` or `poor`: what the dashboard colours
        green, amber and red (specs/remote-link.md says where the lines are)."""
        now = trio.current_time()
        heard = self.last_pong_at if self.last_pong_at is not None else self.started
        if self.pinging and now - heard > 3 * self.ping_interval + (self.rtt or 0.0):
            return "poor"  # no answer to three pings
        if self.last_stale_at is not None and now - self.last_stale_at < STALE_RECENT:
            return "poor"
        if self.rtt is None:
            return "unknown"
        bound = self.max_age if self.max_age is not None else 0.4
        expected = self.rtt / 2 + 2 * self.jitter  # the age most commands stay under
        if expected > bound:
            return "poor"
        return "fair" if expected > bound / 2 else "good"

    def as_dict(self) -> dict[str, Any]:
        """The link as the robot's details show it (seconds)."""
        return {
            "quality": self.quality(),
            "rtt": self.rtt,
            "rtt_min": self.rtt_min,
            "jitter": self.jitter,
            "last_age": self.last_age,
            "stamped": self.stamped,
            "dropped_stale": self.stale,
            "max_age": self.max_age,
        }
