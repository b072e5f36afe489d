"""Serving a file from a folder without letting the request name anything outside it."""

from __future__ import annotations

from pathlib import Path

from quart import Response, send_from_directory
from werkzeug.exceptions import NotFound

from arena.protocol.errors import ArenaError, ErrorCode


async def send_folder_file(folder: Path, name: str, missing: str) -> Response:
    """The file `name` inside `folder`, or `ArenaError(NOT_FOUND, missing)`.

    `send_from_directory` refuses names that would leave the folder (`..`, absolute paths).
    """
    try:
        response: Response = await send_from_directory(folder, name)
    except NotFound:
        raise ArenaError(ErrorCode.NOT_FOUND, missing) from None
    return response
