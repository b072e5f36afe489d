"""REST for the policies a robot may run: `GET /api/robots/{id}/policies` lists the folders of
the robot's tenant's policy folder that hold a LeRobot policy (`config.json`), by the names
`POST .../master {"type": "policy", "path": NAME}` takes (the dashboard's "Attach policy").

Only the tenant's own folder is read; a symbolic link out of it is not listed (attaching would
refuse it), and the listing is bounded however many folders there are.
"""

from __future__ import annotations

import json
import os
import re
from itertools import islice
from pathlib import Path
from typing import Any

from quart import Blueprint, current_app

from arena.protocol.rest import FILE_NAME
from arena.server.base import ArenaApp
from arena.server.drivers import inside, tenant_folder
from arena.server.recordings_api import off_the_loop

blueprint = Blueprint("policies", __name__)

#: Entries of the folder looked at (another tenant's folder among them, for the default
#: tenant's), and policies listed at most (`truncated` says when more were there).
MAX_SCANNED = 10_000
MAX_LISTED = 500
#: Bytes of a policy's config.json read for its `type` (LeRobot's are about 2 KiB).
MAX_CONFIG_BYTES = 65_536


def _policy_type(config: Path) -> str | None:
    """The policy's type (`act`, `diffusion`...) as its config.json says, None if unread."""
    try:
        with config.open("rb") as file:
            data = json.loads(file.read(MAX_CONFIG_BYTES))
    except (OSError, ValueError):
        return None
    kind = data.get("type") if isinstance(data, dict) else None
    return kind if isinstance(kind, str) else None


def list_policies(folder: Path) -> dict[str, Any]:
    """The policies in `folder` (a tenant's): `{policies: [{name, type}], truncated}`, by name."""
    found: list[dict[str, Any]] = []
    truncated = False
    try:
        with os.scandir(folder) as entries:
            scanned = list(islice(entries, MAX_SCANNED + 1))
    except OSError:  # no folder yet: no policy
        scanned = []
    if len(scanned) > MAX_SCANNED:
        scanned, truncated = scanned[:MAX_SCANNED], True
    for entry in sorted(scanned, key=lambda entry: entry.name):
        path = Path(entry.path)
        config = path / "config.json"
        if not re.fullmatch(FILE_NAME, entry.name) or not config.is_file():
            continue
        if not (inside(path, folder) and inside(config, folder)):
            continue  # a link out of the tenant's folder, which attaching refuses
        if len(found) == MAX_LISTED:
            truncated = True
            break
        found.append({"name": entry.name, "type": _policy_type(config)})
    return {"policies": found, "truncated": truncated}


@blueprint.get("/api/robots/<robot_id>/policies")
async def policies(robot_id: str) -> dict[str, Any]:
    """The policies of the robot's tenant's policy folder, by name."""
    app: ArenaApp = current_app  # type: ignore[assignment]
    robot = app.manager.get(robot_id)
    folder = tenant_folder(Path(app.arena_config.policy_dir), robot.tenant)
    return await off_the_loop(list_policies, folder)
