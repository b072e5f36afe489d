"""A move the collision guard stopped after it was accepted, told to whoever commanded it.

The guard checks a command's way before accepting it and every target on the way; a target
that would collide (a keep-out box set meanwhile, a stream's braking past its goal) stops the
motion where it is (`RobotCore._advance`). The commander is told: a master on its link (an
`error` on its socket), and everyone by a `COLLISION` fault, recorded. See specs/motion.md.
"""

from __future__ import annotations

import logging
import time as wallclock
from typing import Any

from arena.protocol.errors import ErrorCode, Severity
from arena.robot.core import RobotCore
from arena.robot.events import FaultReported, MasterNotice
from arena.robot.peers import Peers

log = logging.getLogger(__name__)


def report_stop(actor: Any, now: float) -> FaultReported:
    """The fault that tells of the stop of `actor`'s core (taken: told once), its master told
    too. (`actor` is an `arena.robot.actor.Actor`, which calls this.)"""
    core: RobotCore = actor.core
    peers: Peers[Any, Any] = actor.peers
    robot_id: str = actor.robot_id
    stop = core.take_stop()
    assert stop is not None
    source, hit = stop
    message = (
        f"The move was stopped on its way: going on would bring {hit} together; "
        "the arm holds where it stopped."
    )
    log.warning("robot %s: %s", robot_id, message)
    master = peers.master_named(source)
    if master is not None:
        master.link.notices.put(MasterNotice("stopped", ErrorCode.COLLISION, message))
    told = (ErrorCode.COLLISION, message, Severity.WARNING, None, now, wallclock.time())
    return FaultReported(robot_id, source, *told)
