"""Capture access: probing, and frames streamed at a processing resolution.

A capture is a video file or a folder of photos (:mod:`facecap_core.photos`); every function
here takes either, and a photo folder's frames are its photos in file-name order. Frames are
decoded one at a time (never the whole video in memory), turned upright by the container's
display rotation (phones store portrait video as landscape + a rotation) or the photo's EXIF
orientation, and resized to a processing width. Any frame rate and resolution FFmpeg
decodes is accepted.
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import av
import cv2
import numpy as np

from facecap_core.errors import InputError
from facecap_core.photos import list_photos, probe_photos, read_photo


@dataclass(frozen=True)
class VideoInfo:
    """What a video holds, as displayed (after rotation)."""

    path: Path
    width: int
    height: int
    fps: float
    frame_count: int
    duration_s: float
    rotation_deg: int  # counter-clockwise turn applied to decoded frames for display
    codec: str


@dataclass
class Frame:
    index: int
    time: float
    image: np.ndarray  # uint8 (H, W, 3) RGB, or (H, W) grey


def _open(path: Path):
    if not path.is_file():
        raise InputError(f"video not found: {path}")
    try:
        container = av.open(str(path))
    except Exception as exc:  # PyAV raises FFmpeg errors of many classes for junk files
        raise InputError(f"{path} is not a readable video ({type(exc).__name__}); give an "
                         "MP4/MOV file from a camera") from None
    if not container.streams.video:
        container.close()
        raise InputError(f"{path} has no video stream (audio only?); give a video file")
    return container


def _video_stream(container):
    """The capture's stream: of the video streams that are not a cover image or thumbnails,
    the one with the most frames (then pixels), as a phone may store a preview stream
    first."""
    streams = list(container.streams.video)
    stills = ("attached_pic", "still_image", "timed_thumbnails")
    moving = [s for s in streams
              if not any(s.disposition & getattr(type(s.disposition), d, 0) for d in stills)]
    return max(moving or streams, key=lambda s: (s.frames or 0, s.width * s.height))


def is_photo_folder(path: str | Path) -> bool:
    """Whether a capture path is a folder of photos (else it is a video file)."""
    return Path(path).is_dir()


def _decoding_errors() -> tuple[type[BaseException], ...]:
    """What PyAV raises when FFmpeg cannot decode the stream (the file's fault, not ours)."""

    return (av.error.FFmpegError, EOFError)


def _display_rotation(frame, path: Path) -> int:
    """The frame's counter-clockwise display rotation: a quarter turn, or refused (a
    frame shown at 45° cannot be turned upright without cropping it)."""
    rotation = int(round(getattr(frame, "rotation", 0) or 0)) % 360
    if rotation % 90:
        raise InputError(f"{path} is to be shown turned by {rotation}° (its display matrix); "
                         "only quarter turns are supported: export it upright")
    return rotation


def probe(path: str | Path) -> VideoInfo:
    """Size, rate, length and rotation of a video (decodes its first frame)."""
    path = Path(path)
    if is_photo_folder(path):
        photos = probe_photos(path)
        return VideoInfo(path, photos.width, photos.height, 0.0, len(photos.paths), 0.0, 0,
                         "photos")
    container = _open(path)
    try:
        stream = _video_stream(container)
        try:
            first = next(container.decode(stream))
        except StopIteration:
            raise InputError(f"{path} has a video track with no frames in it; give the "
                             "capture's video file") from None
        except _decoding_errors() as exc:
            raise InputError(f"{path}: the first frame cannot be decoded ({type(exc).__name__});"
                             " the file is damaged or truncated") from None
        rotation = _display_rotation(first, path)
        w, h = first.width, first.height
        if rotation in (90, 270):
            w, h = h, w
        fps = float(stream.average_rate or stream.guessed_rate or 0) or 30.0
        duration = (float(stream.duration * stream.time_base) if stream.duration
                    else float(container.duration or 0) / 1e6)
        count = stream.frames or int(round(duration * fps))
        return VideoInfo(path, w, h, fps, count, duration, rotation, stream.codec_context.name)
    finally:
        container.close()


def stored_frame_count(path: str | Path) -> int:
    """Video frames the file really holds: its packets, read without decoding (fast). A
    file cut short holds fewer than its header's count, which :func:`probe` reports."""
    path = Path(path)
    if is_photo_folder(path):
        return len(list_photos(path))
    container = _open(path)
    try:
        return sum(1 for packet in container.demux(_video_stream(container)) if packet.size)
    except _decoding_errors() as exc:
        raise InputError(f"{path}: reading stopped ({type(exc).__name__}); the file is damaged "
                         "or truncated") from None
    finally:
        container.close()


def processing_size(width: int, height: int, target_width: int | None) -> tuple[int, int]:
    """(w, h) with the aspect ratio kept, at most ``target_width`` wide (no upscaling)."""
    if target_width is None or target_width >= width:
        return width, height
    return int(target_width), max(1, int(round(height * target_width / width)))


def _upright(image: np.ndarray, rotation: int) -> np.ndarray:
    return np.ascontiguousarray(np.rot90(image, k=rotation // 90)) if rotation else image


READ_AHEAD = 4
"""Frames :func:`iter_frames` decodes ahead of its caller."""


def iter_frames(path: str | Path, width: int | None = None, grey: bool = False,
                indices: Iterable[int] | None = None) -> Iterator[Frame]:
    """Frames in order, upright, at most ``width`` pixels wide; only ``indices`` if given.
    They are decoded up to :data:`READ_AHEAD` frames ahead in a thread of their own (the
    decoder and the resize let go of the GIL): a caller's work on a frame (tracking,
    detection, a PNG's encoding) runs beside the decoding of the next."""
    return _read_ahead(_decoded(path, width, grey, indices), READ_AHEAD)


_END = object()


def _read_ahead(frames: Iterator[Frame], count: int) -> Iterator[Frame]:
    """``frames`` made in a thread, at most ``count`` ahead of the caller; what the thread
    raises is raised here, and a caller that stops early stops the thread."""
    ahead: queue.Queue = queue.Queue(count)
    stop = threading.Event()

    def put(item) -> bool:
        while not stop.is_set():
            try:
                ahead.put(item, timeout=0.05)
                return True
            except queue.Full:
                continue
        return False

    def produce() -> None:
        try:
            for frame in frames:
                if not put(frame):
                    return
            put(_END)
        except BaseException as exc:  # noqa: BLE001 - raised again in the caller's thread
            put(exc)
        finally:
            frames.close()

    thread = threading.Thread(target=produce, name="frames", daemon=True)
    thread.start()
    try:
        while (item := ahead.get()) is not _END:
            if isinstance(item, BaseException):
                raise item
            yield item
    finally:
        stop.set()
        thread.join()


def _decoded(path: str | Path, width: int | None, grey: bool,
             indices: Iterable[int] | None) -> Iterator[Frame]:
    path = Path(path)
    wanted = None if indices is None else sorted(set(int(i) for i in indices))
    if wanted == []:
        return
    if is_photo_folder(path):
        yield from _iter_photos(path, width, grey, wanted)
        return
    container = _open(path)
    try:
        stream = _video_stream(container)
        stream.thread_type = "AUTO"
        last = wanted[-1] if wanted else None
        pos, shape = 0, None
        for index, frame in enumerate(container.decode(stream)):
            if last is not None and index > last:
                break
            # Every stage assumes one image size (tracks, cameras, depth maps): a stream
            # that changes it midway (spliced recordings) is refused, not half-processed.
            if shape is None:
                shape = (frame.width, frame.height)
            elif (frame.width, frame.height) != shape:
                raise InputError(f"{path} changes resolution at frame {index} ({shape[0]}x"
                                 f"{shape[1]} to {frame.width}x{frame.height}); re-export it "
                                 "at one resolution")
            if wanted is not None:
                if index != wanted[pos]:
                    continue
                pos += 1
            image = _resize(_upright(frame.to_ndarray(format="gray" if grey else "rgb24"),
                                     _display_rotation(frame, path)), width)
            t = float(frame.time) if frame.time is not None else index / float(stream.average_rate or 30)
            yield Frame(index, t, image)
            if wanted is not None and pos == len(wanted):
                break
    except _decoding_errors() as exc:
        raise InputError(f"{path}: decoding stopped ({type(exc).__name__}); the file is "
                         "damaged or truncated") from None
    finally:
        container.close()


def _resize(image: np.ndarray, width: int | None) -> np.ndarray:
    w, h = processing_size(image.shape[1], image.shape[0], width)
    if (w, h) != (image.shape[1], image.shape[0]):
        image = cv2.resize(image, (w, h), interpolation=cv2.INTER_AREA)
    return image


def _iter_photos(folder: Path, width: int | None, grey: bool,
                 wanted: list[int] | None) -> Iterator[Frame]:
    paths = list_photos(folder)
    for index in range(len(paths)) if wanted is None else wanted:
        if index >= len(paths):
            break  # as a video ends: callers report the frames they did not get
        yield Frame(index, float(index), _resize(read_photo(paths[index], grey), width))


def read_frames(path: str | Path, indices: Iterable[int], width: int | None = None,
                grey: bool = False) -> dict[int, np.ndarray]:
    """The requested frames as {index: image} (one sequential pass over the video)."""
    return {f.index: f.image for f in iter_frames(path, width, grey, indices)}
