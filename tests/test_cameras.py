"""Cameras and episodes: REST, the live MJPEG stream, faults, and what goes into recordings.

Capture threads run on real time; every test waits for events (frames counted, a fault
reported), never for a fixed time.
"""

from __future__ import annotations

import socket
import time
from collections.abc import Callable
from fractions import Fraction
from pathlib import Path
from typing import Any

import av
import foxglove.messages
import numpy as np
import pytest
import trio
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

from arena.protocol.errors import ErrorCode, Severity
from arena.recording import images
from arena.recording.mcap_file import read_recording, write_recording
from arena.robot.events import FaultReported
from arena.robot.manager import RobotManager
from arena.robot.safety import Mode
from arena.sensors import camera as camera_module
from arena.sensors.camera import Cameras, CameraSpec
from arena.sensors.sources import JpegEncoder, pattern_image, read_pattern_counter
from arena.server import sensors_api
from tests.conftest import RunningServer, eventually

TEST_CAMERA = {"name": "front", "source": "test-pattern", "fps": 30, "width": 320, "height": 240}


def jpeg_rgb(jpeg: bytes) -> np.ndarray:
    """A JPEG decoded to an RGB array."""
    codec = av.CodecContext.create("mjpeg", "r")
    (frame,) = codec.decode(av.Packet(jpeg))
    return frame.to_ndarray(format="rgb24")


def test_pattern_frames_carry_their_number_through_jpeg() -> None:
    encoder = JpegEncoder(640, 480, 30)
    for seq in (0, 1, 2, 255, 4097, 65535, 65536 + 7):
        jpeg = encoder.encode_rgb(pattern_image(seq, 640, 480))
        assert jpeg[:2] == b"\xff\xd8" and jpeg[-2:] == b"\xff\xd9"  # a whole JPEG
        image = jpeg_rgb(jpeg)
        assert image.shape == (480, 640, 3)
        assert read_pattern_counter(image) == seq % 65536
    # consecutive frames differ everywhere, not only in the counter
    assert (pattern_image(1, 64, 48)[40:] != pattern_image(2, 64, 48)[40:]).any()


def test_camera_specs_are_checked() -> None:
    CameraSpec("front", "test-pattern").check()
    CameraSpec("wrist_2", "/dev/video2", 60, 1920, 1080).check()
    for bad in (
        CameraSpec("", "test-pattern"),
        CameraSpec("a/b", "test-pattern"),
        CameraSpec("front", "http://example.com/cam"),
        CameraSpec("front", "file:"),
        CameraSpec("front", "test-pattern", fps=0),
        CameraSpec("front", "test-pattern", width=641),
        CameraSpec("front", "test-pattern", height=2000),
    ):
        with pytest.raises(Exception) as caught:
            bad.check()
        assert getattr(caught.value, "code", None) is ErrorCode.INVALID_BODY


def test_compressed_images_decode_with_foxglove_schema_and_ours() -> None:
    from arena.robot.events import CameraFrame

    jpeg = JpegEncoder(64, 48, 30).encode_rgb(pattern_image(3, 64, 48))
    frame = CameraFrame("arm", "front", 3, 1.0, 2.0, 64, 48, jpeg)
    data = images.encode(frame, 1_700_000_000_123_456_789)
    files = descriptor_pb2.FileDescriptorSet.FromString(
        bytes(foxglove.messages.CompressedImage.get_schema().data)
    )
    pool = descriptor_pool.DescriptorPool()
    for file in files.file:
        pool.Add(file)
    message = message_factory.GetMessageClass(
        pool.FindMessageTypeByName("foxglove.CompressedImage")
    ).FromString(data)
    assert message.SerializeToString() == data
    assert (message.timestamp.seconds, message.timestamp.nanos) == (1_700_000_000, 123_456_789)
    assert (message.format, message.frame_id, message.data) == ("jpeg", "arm/cameras/front", jpeg)
    ours = images.decode(data)
    assert (ours.stamp, ours.format, ours.frame_id, ours.data) == (
        1_700_000_000_123_456_789,
        "jpeg",
        "arm/cameras/front",
        jpeg,
    )
    with pytest.raises(ValueError):
        images.decode(b"\x0a\xff")  # a length past the end


def write_video(path: Path, frames: int, width: int = 160, height: int = 120) -> None:
    """A small MPEG-4 file of test-pattern frames."""
    with av.open(str(path), "w") as container:
        stream = container.add_stream("mpeg4", rate=Fraction(30, 1))
        stream.width, stream.height, stream.pix_fmt = width, height, "yuv420p"
        for seq in range(frames):
            picture = av.VideoFrame.from_ndarray(pattern_image(seq, width, height), format="rgb24")
            for packet in stream.encode(picture):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)


async def test_rest_cameras_attach_list_frame_and_detach(
    server: RunningServer, tmp_path: Path
) -> None:
    video = tmp_path / "clip.mp4"
    write_video(video, 12)
    async with server.client() as http:
        base = "/api/robots/demo-arm/cameras"
        assert (await http.get(base)).json() == {"cameras": []}
        created = await http.post(base, json=TEST_CAMERA)
        assert created.status_code == 201, created.text
        assert created.json()["stream"] == f"{base}/front/stream"
        # a file source, looped: more frames than the file holds
        looped = await http.post(base, json={"name": "clip", "source": f"file:{video}", "fps": 60})
        assert looped.status_code == 201, looped.text
        clip = server.app.cameras.get("demo-arm", "clip")
        await eventually(lambda: clip.frames > 30)
        assert clip.error is None
        # refusals: a taken name, a bad body, a source that cannot open, an unknown robot
        taken = await http.post(base, json=TEST_CAMERA)
        assert (taken.status_code, taken.json()["error"]["code"]) == (409, "CAMERA_EXISTS")
        bad = await http.post(base, json={**TEST_CAMERA, "name": "x y"})
        assert (bad.status_code, bad.json()["error"]["code"]) == (422, "INVALID_BODY")
        extra = await http.post(base, json={**TEST_CAMERA, "name": "b", "colour": 1})
        assert (extra.status_code, extra.json()["error"]["code"]) == (400, "UNKNOWN_FIELD")
        missing = await http.post(base, json={"name": "gone", "source": f"file:{tmp_path}/no.mp4"})
        assert (missing.status_code, missing.json()["error"]["code"]) == (422, "CAMERA_FAILED")
        assert "no.mp4" in missing.json()["error"]["message"]
        unknown = await http.post("/api/robots/nope/cameras", json=TEST_CAMERA)
        assert unknown.status_code == 404
        for name in ("c", "d"):
            assert (await http.post(base, json={**TEST_CAMERA, "name": name})).status_code == 201
        fifth = await http.post(base, json={**TEST_CAMERA, "name": "e"})
        assert (fifth.status_code, fifth.json()["error"]["code"]) == (409, "CAMERA_EXISTS")

        listed = (await http.get(base)).json()["cameras"]
        assert [c["name"] for c in listed] == ["front", "clip", "c", "d"]
        frame = await http.get(f"{base}/front/frame")
        assert frame.headers["content-type"] == "image/jpeg"
        assert jpeg_rgb(frame.content).shape == (240, 320, 3)
        # the pattern counts frames made, `seq` frames delivered: they differ by the frames the
        # capture thread dropped while trio was busy (none on a quiet machine)
        made, seq = read_pattern_counter(jpeg_rgb(frame.content)), int(frame.headers["x-frame-seq"])
        front = next(c for c in (await http.get(base)).json()["cameras"] if c["name"] == "front")
        assert seq <= made <= seq + front["dropped"]

        for name in ("clip", "c", "d"):
            assert (await http.delete(f"{base}/{name}")).status_code == 200
        assert (await http.delete(f"{base}/clip")).status_code == 404
        assert [c["name"] for c in (await http.get(base)).json()["cameras"]] == ["front"]
        # deleting the robot stops its cameras
        front = server.app.cameras.get("demo-arm", "front")
        assert (await http.delete("/api/robots/demo-arm")).status_code == 200
        await front.finished.wait()
        assert server.app.cameras.of("demo-arm") == []


async def read_head(stream: trio.SocketStream) -> tuple[bytes, bytes]:
    """An HTTP response head, and whatever of the body came with it."""
    data = b""
    while b"\r\n\r\n" not in data:
        chunk = await stream.receive_some(65536)
        assert chunk, f"closed after {data!r}"
        data += chunk
    head, _, rest = data.partition(b"\r\n\r\n")
    return head, rest


async def read_parts(stream: trio.SocketStream, rest: bytes, count: int) -> list[dict[str, Any]]:
    """`count` parts of a multipart MJPEG stream: their headers and JPEGs."""
    parts: list[dict[str, Any]] = []
    buffer = rest
    while len(parts) < count:
        while b"\r\n\r\n" not in buffer:
            buffer += await stream.receive_some(65536)
        head, _, buffer = buffer.partition(b"\r\n\r\n")
        lines = head.decode().split("\r\n")
        assert lines[0] == "--" + sensors_api.BOUNDARY
        headers = dict(line.lower().split(": ", 1) for line in lines[1:])
        length = int(headers["content-length"])
        while len(buffer) < length + 2:
            buffer += await stream.receive_some(65536)
        parts.append({**headers, "jpeg": buffer[:length]})
        assert buffer[length : length + 2] == b"\r\n"
        buffer = buffer[length + 2 :]
    return parts


async def test_mjpeg_stream_serves_newest_frames_and_drops_a_reader_that_stalls(
    server: RunningServer, monkeypatch: pytest.MonkeyPatch
) -> None:
    host, port = server.url.removeprefix("http://").rsplit(":", 1)
    path = "/api/robots/demo-arm/cameras/front/stream"
    async with server.client() as http:
        created = await http.post(
            "/api/robots/demo-arm/cameras", json={**TEST_CAMERA, "fps": 60, "width": 640}
        )
        assert created.status_code == 201
    camera = server.app.cameras.get("demo-arm", "front")

    stream = await trio.open_tcp_stream(host, int(port))
    request = f"GET {path} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n\r\n"
    await stream.send_all(request.encode())
    head, rest = await read_head(stream)
    assert head.startswith(b"HTTP/1.1 200")
    assert b"multipart/x-mixed-replace; boundary=arenaframe" in head
    parts = await read_parts(stream, rest, 5)
    seqs = [int(part["x-frame-seq"]) for part in parts]
    assert seqs == sorted(seqs) and len(set(seqs)) == 5
    # Each part carries its own image: the counter painted at capture runs ahead of the
    # delivered seq by the frames dropped before it (a busy machine drops some), never behind.
    counters = [read_pattern_counter(jpeg_rgb(part["jpeg"])) for part in parts]
    skips = [counter - seq for counter, seq in zip(counters, seqs, strict=True)]
    assert counters == sorted(counters) and len(set(counters)) == 5
    assert skips == sorted(skips) and skips[0] >= 0 and skips[-1] <= camera.dropped
    assert camera.streams == 1
    await stream.aclose()
    await eventually(lambda: camera.streams == 0)

    # an unknown camera, and a foreign Host (DNS rebinding), are refused with the error shape
    for target, host_header, status in (
        ("/api/robots/demo-arm/cameras/nope/stream", f"127.0.0.1:{port}", b"404"),
        (path, "evil.example:80", b"403"),
    ):
        refused = await trio.open_tcp_stream(host, int(port))
        await refused.send_all(f"GET {target} HTTP/1.1\r\nHost: {host_header}\r\n\r\n".encode())
        head, _ = await read_head(refused)
        assert head.split(b" ")[1] == status
        await refused.aclose()

    # a connection that asked for something else first is sent to a fresh one
    reused = await trio.open_tcp_stream(host, int(port))
    await reused.send_all(f"GET /api/robots HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n\r\n".encode())
    head, body = await read_head(reused)
    length = int(dict(line.split(b": ", 1) for line in head.split(b"\r\n")[1:])[b"content-length"])
    while len(body) < length:
        body += await reused.receive_some(65536)
    await reused.send_all(f"GET {path} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n\r\n".encode())
    head, _ = await read_head(reused)
    assert head.startswith(b"HTTP/1.1 307") and f"location: {path}".encode() in head.lower()
    await reused.aclose()

    # a reader that stops reading loses its stream once a part waits past the deadline
    monkeypatch.setattr(sensors_api, "STREAM_SEND_TIMEOUT", 0.2)
    sock = socket.socket()
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    sock.connect((host, int(port)))
    sock.sendall(request.encode())
    await eventually(lambda: camera.streams_dropped == 1, timeout=60, what="the stall noticed")
    await eventually(lambda: camera.streams == 0)
    sock.close()


class FlakySource:
    """A source that fails after `good` frames, then (reopened) works again."""

    paced = True
    opened = 0

    def __init__(self, good: int) -> None:
        FlakySource.opened += 1
        self.good = good
        self.encoder = JpegEncoder(32, 32, 30)

    def read(self) -> bytes:
        if self.good == 0:
            raise OSError("cable pulled")
        self.good -= 1
        return self.encoder.encode_rgb(pattern_image(0, 32, 32))

    def close(self) -> None:
        pass


async def test_a_failing_camera_is_reported_and_retried_without_stopping_the_arm(
    manager: RobotManager, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(camera_module, "RETRY_INITIAL", 0.01)
    robot = await manager.create_robot("so-arm100", "arm", "arm")
    cameras = Cameras()
    async with trio.open_nursery() as nursery:
        await nursery.start(cameras.run)
        with robot.subscribe() as events:
            # the first source (opened by `attach`) fails after 3 frames, the next one works
            monkeypatch.setattr(camera_module, "open_source", lambda *args: FlakySource(3))
            camera = await cameras.attach(robot, CameraSpec("wrist", "test-pattern", 30, 32, 32))
            monkeypatch.setattr(camera_module, "open_source", lambda *args: FlakySource(1000))
            faults: list[FaultReported] = []
            with trio.fail_after(30):
                async for event in events:
                    if isinstance(event, FaultReported):
                        faults.append(event)
                        if event.code == "CAMERA_RECOVERED":
                            break
            failed, recovered = faults
            assert (failed.peer_id, failed.code, failed.severity) == (
                "camera:wrist",
                "CAMERA_FAILED",
                Severity.WARNING,
            )
            assert "cable pulled" in failed.message
            assert recovered.severity is Severity.INFO
            assert robot.snapshot().mode is Mode.IDLE  # a camera never stops the arm
            frames_then = camera.frames
            await eventually(lambda: camera.frames > frames_then + 3)
            assert camera.failures == 1 and camera.error is None
            await cameras.detach("arm", "wrist")
            assert camera.closed
        nursery.cancel_scope.cancel()


async def test_camera_frames_are_recorded_as_compressed_images(
    start_server: Callable[..., Any], tmp_path: Path
) -> None:
    server = await start_server(demo=True)
    async with server.client() as http:
        assert (await http.post("/api/robots/demo-arm/cameras", json=TEST_CAMERA)).is_success
        camera = server.app.cameras.get("demo-arm", "front")
        await eventually(lambda: camera.frames >= 10)
        before = time.time_ns()
        moved = await http.put(
            "/api/robots/demo-arm/joints", json={"joints": [{"name": "Rotation", "value": 5}]}
        )
        assert moved.is_success, moved.text
        after = time.time_ns()
        await eventually(lambda: camera.frames >= 20)
        assert (await http.delete("/api/robots/demo-arm/cameras/front")).is_success
        captured = camera.frames
        stopped = (await http.post("/api/recordings/current/stop")).json()["stopped"]
    recording = read_recording(Path(server.app.recorder.folder) / stopped)
    frames = [v for v in recording.views if v.topic == "/robots/demo-arm/cameras/front"]
    assert len(frames) == captured  # every frame captured, none lost
    assert frames[0].schema[:2] == ("foxglove.CompressedImage", "protobuf")
    assert frames[0].encoding == "protobuf"
    decoded = [images.decode(frame.data) for frame in frames]
    assert all(image.stamp == frame.log_time for image, frame in zip(decoded, frames, strict=True))
    counters = [read_pattern_counter(jpeg_rgb(image.data)) for image in decoded]
    assert counters == sorted(counters) and len(set(counters)) == len(counters)
    # capture times sit on the recording's clock, among the robot's own records: the frames
    # captured before the command was sent come before its record, those after it after
    (command,) = [m for m in recording.messages if m.kind == "command"]
    assert before - 20_000_000 < command.log_time < after + 20_000_000
    assert frames[0].log_time < before and frames[-1].log_time > after
    earlier = [f for f in frames if f.log_time < command.log_time]
    assert 10 <= len(earlier) < len(frames)
    # `arena recover` (a recording read and written again) keeps every frame as it was
    rewritten = tmp_path / "rewritten.mcap"
    write_recording(recording, rewritten)
    again = [v for v in read_recording(rewritten).views if v.topic == frames[0].topic]
    assert [(f.log_time, f.data) for f in again] == [(f.log_time, f.data) for f in frames]


async def test_episodes_start_stop_discard_and_are_recorded(server: RunningServer) -> None:
    base = "/api/robots/demo-arm/episodes"
    async with server.client() as http:
        assert (await http.get(base)).json() == {
            "active": None,
            "kept": 0,
            "discarded": 0,
            "last": None,
        }
        none = await http.post(f"{base}/stop")
        assert (none.status_code, none.json()["error"]["code"]) == (409, "NO_EPISODE")
        assert (await http.post(f"{base}/discard")).status_code == 409
        empty = await http.post(f"{base}/start", json={"task": ""})
        assert empty.status_code == 422
        blank = await http.post(f"{base}/start", json={"task": "   "})
        assert blank.status_code == 422
        started = await http.post(f"{base}/start", json={"task": "pick up the cube"})
        assert started.status_code == 201
        assert started.json() == {
            "index": 0,
            "task": "pick up the cube",
            "duration": None,
            "discarded": False,
        }
        again = await http.post(f"{base}/start", json={"task": "other"})
        assert (again.status_code, again.json()["error"]["code"]) == (409, "EPISODE_ACTIVE")
        running = (await http.get(base)).json()["active"]
        assert running["index"] == 0 and running["elapsed"] >= 0
        stopped = (await http.post(f"{base}/stop")).json()
        assert stopped["index"] == 0 and stopped["duration"] >= 0
        await http.post(f"{base}/start", json={"task": "stack"})
        assert (await http.post(f"{base}/discard")).json()["discarded"] is True
        # with none running, discard takes back the last kept episode... once
        assert (await http.post(f"{base}/discard")).status_code == 409
        summary = (await http.get(base)).json()
        assert (summary["kept"], summary["discarded"]) == (1, 1)
        name = (await http.post("/api/recordings/current/stop")).json()["stopped"]
    recording = read_recording(Path(server.app.recorder.folder) / name)
    marks = [
        (m.data["change"], m.data["index"], m.data["task"])
        for m in recording.messages
        if m.kind == "episode"
    ]
    assert marks == [
        ("start", 0, "pick up the cube"),
        ("stop", 0, "pick up the cube"),
        ("start", 1, "stack"),
        ("discard", 1, "stack"),
    ]
    assert "/robots/demo-arm/episode" in recording.schemas
