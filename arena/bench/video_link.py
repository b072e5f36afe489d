"""A camera's MJPEG stream to a client across a slow link: how old each frame is when it
arrives, before and after the stream waits for the client (specs/remote-link.md).

    python -m arena.bench.video_link [FILE.json]

A server in this process, a 640x480 test-pattern camera at 30 fps, and a client reading its
stream through `SlowLink` (50 ms each way, 100 kB/s: the link carries about a third of the
camera's frames), for 10 s, on the real clock. "before": the stream writes each newest frame as
soon as the last is written (into the kernel's buffers); "after": once the kernel has handed the
last to the client. Frame age = arrival at the client - the frame's `X-Timestamp`.
"""

from __future__ import annotations

import json
import sys
import time
from functools import partial
from pathlib import Path
from tempfile import TemporaryDirectory
from typing import Any

import httpx
import trio

from arena.bench.slow_link import SlowLink
from arena.server import sensors_api
from arena.server.config import ServerConfig
from arena.server.run import run_server

CAMERA = {"name": "front", "source": "test-pattern", "fps": 30, "width": 640, "height": 480}
SECONDS = 10.0


async def read_stream(port: int, path: str, seconds: float) -> list[tuple[float, float, int]]:
    """(arrival, the frame's timestamp, its size) of each part read for `seconds`."""
    stream = await trio.open_tcp_stream("127.0.0.1", port)
    await stream.send_all(f"GET {path} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n\r\n".encode())
    buffer = b""
    while b"\r\n\r\n" not in buffer:
        buffer += await stream.receive_some(65536)
    buffer = buffer.split(b"\r\n\r\n", 1)[1]
    parts = []
    with trio.move_on_after(seconds):
        while True:
            while b"\r\n\r\n" not in buffer:
                buffer += await stream.receive_some(65536)
            head, buffer = buffer.split(b"\r\n\r\n", 1)
            fields = dict(line.split(": ", 1) for line in head.decode("latin-1").split("\r\n")[1:])
            length = int(fields["Content-Length"])
            while len(buffer) < length + 2:
                buffer += await stream.receive_some(65536)
            buffer = buffer[length + 2 :]
            parts.append((time.time(), float(fields["X-Timestamp"]), length))
    await stream.aclose()
    return parts


async def one_run(wait_for_client: bool) -> dict[str, Any]:
    """The stream across the link, with or without waiting for the client."""
    if not wait_for_client:
        sensors_api.kernel_queue = lambda stream: None
    with TemporaryDirectory() as folder:
        config = ServerConfig(port=0, record=False, recordings_dir=folder)
        stop = trio.Event()
        async with trio.open_nursery() as nursery:
            app, urls = await nursery.start(partial(run_server, config, stop=stop))
            await app.manager.create_robot("so-arm100", robot_id="far")
            async with httpx.AsyncClient(base_url=urls[0]) as http:
                answer = await http.post("/api/robots/far/cameras", json=CAMERA)
                answer.raise_for_status()
            link = SlowLink("127.0.0.1", int(urls[0].rsplit(":", 1)[1]), kernel_buffer=8192)
            await nursery.start(link.serve)
            link.shape(delay=0.05, bandwidth=100_000)
            link.down.buffer_bytes = 65536
            await trio.sleep(1.0)  # the camera runs
            path = "/api/robots/far/cameras/front/stream"
            parts = await read_stream(link.port, path, SECONDS)
            stop.set()
            nursery.cancel_scope.cancel()
    ages = sorted(arrival - stamp for arrival, stamp, _ in parts)
    last_second = [arrival - stamp for arrival, stamp, _ in parts if arrival > parts[-1][0] - 1]
    return {
        "frames_received": len(parts),
        "fps": round(len(parts) / SECONDS, 1),
        "frame_kB": round(sum(size for *_, size in parts) / max(len(parts), 1) / 1000, 1),
        "age_p50_ms": round(ages[len(ages) // 2] * 1000),
        "age_max_ms": round(ages[-1] * 1000),
        "age_in_the_last_second_ms": round(max(last_second) * 1000),
    }


def main() -> dict[str, Any]:
    """Before and after, each in a trio run of its own."""
    return {
        "after (waits for the client)": trio.run(one_run, True),
        "before (writes into the kernel's buffers)": trio.run(one_run, False),
    }


if __name__ == "__main__":
    figures = main()
    text = json.dumps(figures, indent=2)
    print(text)
    if len(sys.argv) > 1:
        Path(sys.argv[1]).write_text(text + "\n", encoding="utf-8")
