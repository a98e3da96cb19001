"""Video in for `repnet video`: a clip file or a camera device decoded to RGB frames with PyAV (FFmpeg's
libraries; the `video` extra), its frame rate and size read from the stream."""

from __future__ import annotations

import re
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from repnet.io.poses import InputFileError

# A camera: /dev/videoN (Linux, v4l2), or its number alone.
_DEVICE = re.compile(r"(/dev/video)?(\d+)")
DEFAULT_DEVICE_FPS = 30.0  # a device's frame rate when its stream gives none


def _av() -> Any:
    """PyAV, imported when a video is opened (ImportError naming `av`: the `video` extra)."""
    import av

    return av


def device_path(source: str) -> str | None:
    """The v4l2 device `source` names (/dev/video0, or 0 where no file of that name is here), None
    for a file."""
    found = _DEVICE.fullmatch(source)
    if found is None or (found.group(1) is None and Path(source).is_file()):
        return None
    return f"/dev/video{found.group(2)}"


@dataclass
class Clip:
    """An open video: its frames, one at a time, as RGB (H, W, 3) uint8."""

    source: str
    container: Any  # av.container.InputContainer
    stream: Any  # av.video.stream.VideoStream
    fps: float
    width: int
    height: int
    frame_count: int | None  # as the container says, if it does
    live: bool  # a camera: frames until it stops, read once
    broken: str | None = None  # why decoding stopped before the stream's end, if it did

    def frames(self, limit: int | None = None) -> Iterator[np.ndarray]:
        """The decoded frames, at most `limit`; InputFileError naming the file when not one frame
        decodes; a stream that breaks off later (a truncated or damaged file) ends there, said in
        `broken`."""
        av = _av()
        count = 0
        try:
            for frame in self.container.decode(self.stream):
                if limit is not None and count >= limit:
                    return
                yield frame.to_ndarray(format="rgb24")
                count += 1
        except av.FFmpegError as err:
            if count == 0:
                raise InputFileError(f"{self.source}: cannot decode its video: {err}") from None
            self.broken = f"{self.source}: decoding stopped at frame {count}: {err}"

    def close(self) -> None:
        """Close the file or device."""
        self.container.close()


def open_clip(source: str) -> Clip:
    """The video at `source`: a file, or a camera device (/dev/videoN or N); InputFileError naming
    it and why when it is missing, not a video or has no video stream."""
    av = _av()
    device = device_path(source)
    if device is None:
        path = Path(source)
        if not path.exists():
            raise InputFileError(f"{source}: no such file")
        if path.is_dir():
            raise InputFileError(f"{source}: a folder, not a video file")
    try:
        container = av.open(device or source, format="v4l2" if device else None)
    except (av.FFmpegError, OSError) as err:
        raise InputFileError(f"{source}: cannot open it as a video: {err}") from None
    if not container.streams.video:
        container.close()
        raise InputFileError(f"{source}: the file has no video stream")
    stream = container.streams.video[0]
    stream.thread_type = "AUTO"  # FFmpeg's frame threads: decoding keeps up with the detector
    rate = stream.average_rate or stream.guessed_rate
    fps = float(rate) if rate else DEFAULT_DEVICE_FPS
    width, height = int(stream.codec_context.width), int(stream.codec_context.height)
    if width <= 0 or height <= 0:
        container.close()
        raise InputFileError(f"{source}: the video stream has no frame size ({width} x {height})")
    count = int(stream.frames) if stream.frames else None
    return Clip(source, container, stream, fps, width, height, count, device is not None)
