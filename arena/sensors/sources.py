"""Where camera frames come from: a device, a video file, or a generated test pattern.

Every source hands out JPEG bytes of the requested size, synchronously (it runs in the camera's
capture process, `capture.py`). PyAV does all of it: V4L2 devices and video files through
FFmpeg's demuxers, and JPEG through FFmpeg's `mjpeg` encoder. A camera that already speaks MJPEG
(most USB webcams) passes its JPEGs through untouched, which costs next to nothing.
"""

from __future__ import annotations

from fractions import Fraction
from typing import Any, Protocol

import numpy as np

_FULL_RANGE = 2  # FFmpeg's AVCOL_RANGE_JPEG
Image = np.ndarray[Any, np.dtype[np.uint8]]
#: The test pattern's frame counter: bits of this many pixels a side, along the top edge.
PATTERN_BIT = 16
PATTERN_BITS = 16


class FrameSource(Protocol):
    """A synchronous supplier of JPEG frames. One that knows when its last frame's picture was
    taken (long before `read` returned) may say so in an attribute `exposed` (`perf_counter`
    seconds); the camera then dates the frame by it."""

    paced: bool  # True when `read` returns at once and the server must keep the rate

    def read(self) -> bytes:
        """The next frame as JPEG; raises `OSError` when the source fails."""
        ...

    def close(self) -> None:
        """Release the device or file."""
        ...


class JpegEncoder:
    """RGB or decoded frames to JPEG at a fixed size (FFmpeg's mjpeg encoder via PyAV)."""

    def __init__(self, width: int, height: int, fps: int) -> None:
        import av

        self._av = av
        self.width, self.height = width, height
        codec: Any = av.CodecContext.create("mjpeg", "w")
        codec.width, codec.height = width, height
        # Full-range 4:2:0, said the current way (the "yuvj" formats are deprecated in FFmpeg).
        codec.pix_fmt = "yuv420p"
        codec.color_range = _FULL_RANGE
        codec.time_base = Fraction(1, fps)
        self._codec = codec

    def encode_rgb(self, image: Image) -> bytes:
        """An HxWx3 uint8 array as JPEG."""
        return self.encode_frame(self._av.VideoFrame.from_ndarray(image, format="rgb24"))

    def encode_frame(self, frame: Any) -> bytes:
        """A PyAV `VideoFrame` of any size and format as JPEG of this encoder's size."""
        frame = frame.reformat(
            width=self.width, height=self.height, format="yuv420p", dst_color_range=_FULL_RANGE
        )
        return b"".join(bytes(packet) for packet in self._codec.encode(frame))


def scale_jpeg(jpeg: bytes, width: int, height: int) -> bytes:
    """A JPEG at another size: decoded, scaled and encoded again by FFmpeg (a policy's input
    size, before the frame leaves the server)."""
    import av

    decoder: Any = av.CodecContext.create("mjpeg", "r")
    (frame,) = decoder.decode(av.Packet(jpeg))
    return JpegEncoder(width, height, 30).encode_frame(frame)


def pattern_image(seq: int, width: int, height: int) -> Image:
    """A frame that changes every frame: a moving colour ramp, with `seq` written along the top
    edge as `PATTERN_BITS` black or white squares (most significant first), so a test can read
    which frame it is looking at even after JPEG and video compression (modulo 2**16; a frame
    narrower than 256 pixels holds width // 16 bits)."""
    x = (np.arange(width, dtype=np.uint16) + (seq * 4) % 256) % 256
    y = np.arange(height, dtype=np.uint16) % 256
    image = np.empty((height, width, 3), np.uint8)
    image[:, :, 0] = x[None, :]
    image[:, :, 1] = y[:, None]
    image[:, :, 2] = (seq * 8) % 256
    image[: PATTERN_BIT * 2, :] = 128
    bits = min(PATTERN_BITS, width // PATTERN_BIT)  # a narrow frame keeps the low bits
    for bit in range(bits):
        on = (seq >> (bits - 1 - bit)) & 1
        x0 = bit * PATTERN_BIT
        image[:PATTERN_BIT, x0 : x0 + PATTERN_BIT] = 255 if on else 0
    return image


def read_pattern_counter(image: Image) -> int:
    """The frame number `pattern_image` wrote into an RGB image (after lossy compression too)."""
    value = 0
    for bit in range(min(PATTERN_BITS, image.shape[1] // PATTERN_BIT)):
        x0 = bit * PATTERN_BIT
        square = image[2 : PATTERN_BIT - 2, x0 + 2 : x0 + PATTERN_BIT - 2]
        value = (value << 1) | int(square.mean() > 128)
    return value


class PatternSource:
    """Generated frames (`test-pattern`): for tests and demos, no hardware needed."""

    paced = True

    def __init__(self, width: int, height: int, fps: int) -> None:
        self._encoder = JpegEncoder(width, height, fps)
        self._seq = 0

    def read(self) -> bytes:
        image = pattern_image(self._seq, self._encoder.width, self._encoder.height)
        self._seq += 1
        return self._encoder.encode_rgb(image)

    def close(self) -> None:
        pass


class FileSource:
    """A video file (`file:PATH`), played at the camera's rate and looped."""

    paced = True

    def __init__(self, path: str, width: int, height: int, fps: int) -> None:
        import av

        try:
            self._container = av.open(path)
        except (OSError, av.error.FFmpegError) as exc:
            raise OSError(f"cannot open {path}: {exc}") from exc
        if not self._container.streams.video:
            self._container.close()
            raise OSError(f"{path} has no video stream")
        self._stream = self._container.streams.video[0]
        self._frames = self._container.decode(self._stream)
        self._encoder = JpegEncoder(width, height, fps)

    def read(self) -> bytes:
        import av

        for _ in range(2):  # at the end, rewind once
            try:
                return self._encoder.encode_frame(next(self._frames))
            except StopIteration:
                self._container.seek(0)
                self._frames = self._container.decode(self._stream)
            except av.error.FFmpegError as exc:
                raise OSError(str(exc)) from exc
        raise OSError("the video file holds no frames")

    def close(self) -> None:
        self._container.close()


class DeviceSource:
    """A V4L2 camera (`/dev/videoN`), asked for MJPEG at the camera's size and rate."""

    paced = False  # the device delivers at its own rate

    def __init__(self, path: str, width: int, height: int, fps: int) -> None:
        import av

        options = {"video_size": f"{width}x{height}", "framerate": str(fps)}
        try:
            try:
                self._container = av.open(
                    path, format="v4l2", options={**options, "input_format": "mjpeg"}
                )
            except av.error.FFmpegError:  # a camera without MJPEG: raw frames, encoded here
                self._container = av.open(path, format="v4l2", options=options)
        except (OSError, av.error.FFmpegError) as exc:
            raise OSError(f"cannot open {path}: {exc}") from exc
        self._stream = self._container.streams.video[0]
        self._passthrough = self._stream.codec_context.name == "mjpeg" and (
            self._stream.codec_context.width,
            self._stream.codec_context.height,
        ) == (width, height)
        self._packets = self._container.demux(self._stream)
        self._encoder = JpegEncoder(width, height, fps)

    def read(self) -> bytes:
        import av

        try:
            for packet in self._packets:
                if packet.size == 0:
                    continue
                if self._passthrough:
                    return bytes(packet)
                for frame in packet.decode():
                    return self._encoder.encode_frame(frame)
        except av.error.FFmpegError as exc:
            raise OSError(str(exc)) from exc
        raise OSError("the camera stopped delivering frames")

    def close(self) -> None:
        self._container.close()


def open_source(source: str, width: int, height: int, fps: int) -> FrameSource:
    """The frame source a camera's `source` names (raises `OSError` if it cannot be opened)."""
    if source == "test-pattern":
        return PatternSource(width, height, fps)
    if source.startswith("file:"):
        return FileSource(source[5:], width, height, fps)
    if source == "twin" or source.startswith("twin:"):  # not a device: a robot's physics slave
        raise OSError("a twin camera renders a physics slave, which whoever attaches it opens")
    return DeviceSource(source, width, height, fps)
