"""The web dashboard: the page built from `arena/dashboard` (`make ui`), served at `/ui/`.

The page is static and public (it holds no secret); it asks for an API key when the server
wants one and talks only to the public REST and WebSocket API.
"""

from __future__ import annotations

from pathlib import Path

from quart import Blueprint, Response, redirect

from arena.protocol.errors import ArenaError, ErrorCode
from arena.server.files import send_folder_file

blueprint = Blueprint("dashboard", __name__)

SOURCE_DIR = Path(__file__).resolve().parent.parent / "dashboard"
BUILD_DIR = SOURCE_DIR / "dist"
NOT_BUILT = "The dashboard is not built: run `make ui` (it needs Node.js and npm)."


def is_built() -> bool:
    """Whether `make ui` has produced the page."""
    return (BUILD_DIR / "index.html").is_file()


@blueprint.get("/ui")
async def dashboard_root() -> Response:
    """The page lives under `/ui/` so that its relative asset paths resolve."""
    return redirect("/ui/")  # type: ignore[return-value]


@blueprint.get("/ui/")
@blueprint.get("/ui/<path:name>")
async def dashboard_file(name: str = "index.html") -> Response:
    """A file of the built page."""
    if not is_built():
        raise ArenaError(ErrorCode.NOT_FOUND, NOT_BUILT)
    response = await send_folder_file(BUILD_DIR, name, f"The dashboard has no file {name!r}.")
    response.cache_control.no_cache = True  # a rebuilt page shows at the next load
    return response
