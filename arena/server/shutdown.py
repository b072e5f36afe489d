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
    """Tell every robot the stop is planned, before the robots stop: each hardware slave, however
    it was attached (over REST, by the demo, by a program that embeds the server), leaves its
    servos as its `estop` setting says when its driver ends (a detach leaves them limp)."""
    for robot in app.manager.robots():
        robot.plan_stop()
