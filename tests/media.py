"""Small test videos written with PyAV, shared by the test modules."""

from __future__ import annotations

import fractions
from pathlib import Path

import av


def write_video(path: Path, frames, fps: float = 30, rotation: int = 0, times=None,
                faststart: bool = False, codec: str = "libx264") -> Path:
    """An MP4 (H.264 unless ``codec``); ``times`` (seconds) gives a variable frame rate."""
    options = {"movflags": "faststart"} if faststart else {}
    with av.open(str(path), "w", format="mp4", options=options) as container:
        stream = container.add_stream(codec, rate=fps)
        stream.height, stream.width = frames[0].shape[:2]
        stream.pix_fmt = "yuvj420p" if codec == "mjpeg" else "yuv420p"
        if codec == "libx264":
            stream.options = {"preset": "ultrafast", "crf": "0"}  # lossless: same pixels at any rate
        if times is not None:
            stream.codec_context.time_base = fractions.Fraction(1, 1000)
        if rotation:
            stream.set_display_rotation(rotation)
        for i, image in enumerate(frames):
            frame = av.VideoFrame.from_ndarray(image, format="rgb24")
            if times is not None:
                frame.pts, frame.time_base = round(times[i] * 1000), fractions.Fraction(1, 1000)
            else:
                frame.pts = i
            for packet in stream.encode(frame):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)
    return path
