"""The planned stop: what SIGTERM (or Ctrl-C) does to a running server.

The first signal stops the server as planned: new connections are refused, every WebSocket is
closed with 1001 (going away), every robot stops, each hardware slave leaves its servos as its
own `estop` setting says (held where they are, torque on for `hold`, off for `torque-off`), and the
recording is finished with its index. A second signal means "now": the graceful part is cut
short (the robots' stop and the recording's close still run, each bounded).
"""

from __future__ import annotations

import logging
import signal

import trio

from arena.server.base import ArenaApp

log = logging.getLogger(__name__)

SIGNALS = (signal.SIGINT, signal.SIGTERM)


async def stop_on_signals(stop: trio.Event, now: trio.CancelScope) -> None:
    """The first SIGINT or SIGTERM sets `stop`; the next one cancels `now`."""
    with trio.open_signal_receiver(*SIGNALS) as signals:
        async for signum in signals:
            name = signal.Signals(signum).name
            if not stop.is_set():
                log.info("received %s: stopping (again to stop at once)", name)
                stop.set()
                continue
            log.warning("received %s again: stopping at once", name)
            now.cancel()
            return


def leave_slaves_as_set(app: ArenaApp) -> None:
    """Tell each hardware slave the stop is planned, before the robots stop: when its driver
    ends it leaves the servos as its `estop` setting says (a detach leaves them limp)."""
    for driver in app.hardware.drivers():
        planned_stop = getattr(driver, "planned_stop", None)
        if planned_stop is not None:
            planned_stop()
