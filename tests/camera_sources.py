"""Stand-in camera sources that tests open in a real capture process (`arena.sensors.capture`):
a camera that fails after some frames, one that hangs in native code holding its interpreter's
lock, and one that crashes. Each takes its parameters as a capture `Recipe` gives them.
"""

from __future__ import annotations

import ctypes
import os
from pathlib import Path

from arena.sensors.sources import JpegEncoder, pattern_image


class Flaky:
    """Fails ("cable pulled") after `good` frames the first time it is opened (counted in the
    file `opens`), and works from the second opening on."""

    paced = True

    def __init__(self, good: int, opens: str) -> None:
        path = Path(opens)
        count = int(path.read_text() or "0") if path.exists() else 0
        path.write_text(str(count + 1))
        self.good = good if count == 0 else 1_000_000
        self.encoder = JpegEncoder(32, 32, 30)

    def read(self) -> bytes:
        if self.good == 0:
            raise OSError("cable pulled")
        self.good -= 1
        return self.encoder.encode_rgb(pattern_image(0, 32, 32))

    def close(self) -> None:
        pass


class Hangs:
    """Gives `good` frames, then, as a renderer stuck in a driver would, sleeps in C with the
    GIL held (`ctypes.PyDLL` keeps it across the call), first writing its pid to `marker`."""

    paced = True

    def __init__(self, good: int, marker: str) -> None:
        self.good = good
        self.marker = Path(marker)
        self.encoder = JpegEncoder(32, 32, 30)

    def read(self) -> bytes:
        if self.good == 0:
            self.marker.write_text(str(os.getpid()))
            ctypes.PyDLL(None).sleep(3600)
        self.good -= 1
        return self.encoder.encode_rgb(pattern_image(0, 32, 32))

    def close(self) -> None:
        pass


class Crashes:
    """Dies at its first frame as a native library that faults does (SIGABRT)."""

    paced = True

    def read(self) -> bytes:
        os.abort()

    def close(self) -> None:
        pass
