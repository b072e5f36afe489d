"""Health for orchestrators: `/healthz` (the process answers) and `/readyz` (ready for work).

Both are public (an orchestrator's probe carries no key) and say only what is not ready, never a
setting or a key. A readiness probe that fails takes the server out of a load balancer's pool or
restarts the container (Docker's `HEALTHCHECK`), so `/readyz` is 503 exactly when a client
would find the server unable to do its job: not listening, shutting down, a recorder that is
failing to write, or a slave of some robot whose hardware or link is gone.
"""

from __future__ import annotations

from typing import Any

from quart import Blueprint, current_app

from arena.robot.manager import RobotManager
from arena.server.base import ArenaApp

blueprint = Blueprint("health", __name__)

#: The probes' paths: the app lets them through without a key.
HEALTH_PATHS = frozenset({"/healthz", "/readyz"})


def not_ready(app: ArenaApp) -> list[str]:
    """Why the server is not ready, one sentence each (empty: ready)."""
    reasons = []
    if app.own_url is None:
        reasons.append("not listening yet")
    if app.shutting_down.is_set():
        reasons.append("shutting down")
    if app.recorder.active and app.recorder.error is not None:
        reasons.append(f"the recorder cannot write: {app.recorder.error}")
    reasons.extend(_slaves_not_connected(app.manager))
    if app.declared is not None:  # declared parts not up yet, being retried
        reasons.extend(app.declared.not_ready())
    return reasons


def _slaves_not_connected(manager: RobotManager) -> list[str]:
    reasons = []
    for robot in manager.robots():
        for slave in robot.snapshot().slaves:
            if not slave.connected:
                why = f" ({slave.last_error})" if slave.last_error else ""
                reasons.append(
                    f"robot {robot.robot_id}: slave {slave.peer_id} is disconnected{why}"
                )
    return reasons


@blueprint.get("/healthz")
async def healthz() -> dict[str, Any]:
    """The process answers: 200 whenever the event loop serves requests."""
    return {"status": "ok"}


@blueprint.get("/readyz")
async def readyz() -> tuple[dict[str, Any], int]:
    """Ready for work: 200 with `{"status": "ready"}`, else 503 with the reasons."""
    app: ArenaApp = current_app  # type: ignore[assignment]
    reasons = not_ready(app)
    status = "not ready" if reasons else "ready"
    return {"status": status, "reasons": reasons}, (503 if reasons else 200)
