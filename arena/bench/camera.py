"""`arena bench camera`: what one camera costs and how fresh its frames reach a viewer.

One robot on a server of its own (recording on). The server's CPU (its recording process
included) is measured over the same window without a camera, then with a 640x480 test-pattern
camera at 30 fps whose MJPEG stream one client reads. The client stamps each part on arrival
against the capture time the part carries (`X-Timestamp`, the same machine's clock): capture
to client. Frames the capture thread dropped, parts the stream skipped (the newest wins), and
frames the recording kept are counted.
"""

from __future__ import annotations

import asyncio
import time

import httpx

from arena.bench.common import Server, create_bench_robot, percentile

CAMERA = {"name": "bench", "source": "test-pattern", "fps": 30, "width": 640, "height": 480}


async def _cpu_over(server: Server, seconds: float) -> float:
    """The server's CPU, in percent of one core, over `seconds`."""
    before = server.cpu_seconds()
    await asyncio.sleep(seconds)
    return (server.cpu_seconds() - before) / seconds * 100


async def _read_stream(server: Server, path: str, until: float) -> tuple[list[float], int, int]:
    """Parts of an MJPEG stream until `until`: (latencies in s, parts, seq gaps)."""
    host, port = server.url.split("//")[1].rsplit(":", 1)
    reader, writer = await asyncio.open_connection(host, int(port))
    writer.write(f"GET {path} HTTP/1.1\r\nHost: {host}:{port}\r\n\r\n".encode())
    await reader.readuntil(b"\r\n\r\n")
    latencies: list[float] = []
    gaps, last = 0, None
    while time.monotonic() < until:
        head = await reader.readuntil(b"\r\n\r\n")
        arrived = time.time()
        headers = dict(
            line.split(": ", 1) for line in head.decode().split("\r\n")[1:] if ": " in line
        )
        await reader.readexactly(int(headers["Content-Length"]) + 2)
        seq = int(headers["X-Frame-Seq"])
        latencies.append(arrived - float(headers["X-Timestamp"]))
        if last is not None and seq != last + 1:
            gaps += seq - last - 1
        last = seq
    writer.close()
    return latencies, len(latencies), gaps


async def camera(server: Server, seconds: float = 10.0) -> dict[str, float]:
    """CPU of one camera (capture, JPEG, recording, one stream), capture-to-client latency,
    and frames lost on the way."""
    async with httpx.AsyncClient(base_url=server.url, timeout=30) as http:
        await create_bench_robot(http, "cam-arm")
        await asyncio.sleep(1.0)
        idle = await _cpu_over(server, seconds)
        created = await http.post("/api/robots/cam-arm/cameras", json=CAMERA)
        created.raise_for_status()
        stream = created.json()["stream"]
        await asyncio.sleep(1.0)
        reading = asyncio.create_task(_read_stream(server, stream, time.monotonic() + seconds))
        busy = await _cpu_over(server, seconds)
        latencies, parts, skipped = await reading
        stats = (await http.get("/api/robots/cam-arm/cameras/bench")).json()
        await http.delete("/api/robots/cam-arm/cameras/bench")
        recorder = (await http.get("/api/recordings")).json()
    return {
        "camera_cpu_percent": busy - idle,
        "camera_idle_server_cpu_percent": idle,
        "camera_to_client_p50_ms": percentile(latencies, 0.5) * 1000,
        "camera_to_client_p99_ms": percentile(latencies, 0.99) * 1000,
        "camera_stream_parts": float(parts),
        "camera_stream_skipped": float(skipped),
        "camera_frames": float(stats["frames"]),
        "camera_dropped_at_capture": float(stats["dropped"]),
        "camera_recording_dropped": float(recorder["recorder"]["dropped"]),
    }
