"""What `arena export --format lerobot` checks before it writes, and what it leaves when it
fails (`dataset.export_lerobot`): a dataset's cameras keep one size, and a failed export leaves
no half-written folder to block a retry."""

from __future__ import annotations

import contextlib
import shutil
from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

from arena.protocol.errors import ArenaError, ErrorCode

#: (episode index, each of its frames' JPEG by camera name): what the sizes are checked on.
Episodes = Sequence[tuple[int, Sequence[Mapping[str, bytes]]]]


def _size(shape: Sequence[int]) -> str:
    """An image's (height, width, channels) as WIDTHxHEIGHT."""
    return f"{shape[1]}x{shape[0]}"


def camera_shapes(episodes: Episodes, shape_of: Callable[[bytes], Any]) -> dict[str, Any]:
    """Each camera's image shape, from the first frame; `ArenaError(INVALID_RECORDING)` naming
    the camera, both sizes and both episodes where an episode's first or last frame differs
    (a camera re-attached at another size), before anything is written."""
    (first, frames), *_ = episodes
    shapes = {name: shape_of(jpeg) for name, jpeg in frames[0].items()}
    for index, found in episodes:
        for frame in (found[0], found[-1]):
            for name, jpeg in frame.items():
                shape = shape_of(jpeg)
                if shape != shapes.get(name):
                    was = _size(shapes[name]) if name in shapes else "no such camera"
                    raise ArenaError(
                        ErrorCode.INVALID_RECORDING,
                        f"Camera {name!r} is {_size(shape)} in episode {index} but {was} in "
                        f"episode {first}: a dataset's cameras keep one size; export the "
                        "episodes of each size apart (one recording each).",
                    )
    return shapes


@contextlib.contextmanager
def nothing_left_on_failure(root: Path) -> Iterator[None]:
    """Remove what was written into `root` (empty or missing before) if the body fails."""
    made = not root.exists()
    try:
        yield
    except BaseException:
        if made:
            shutil.rmtree(root, ignore_errors=True)
        else:
            for entry in root.iterdir():
                if entry.is_dir() and not entry.is_symlink():
                    shutil.rmtree(entry, ignore_errors=True)
                else:
                    entry.unlink(missing_ok=True)
        raise
