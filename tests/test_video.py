import numpy as np
import pytest

from facecap_core.errors import InputError
from facecap_core.video import iter_frames, probe, read_frames
from tests.media import write_video


@pytest.fixture
def clip(tmp_path):
    frames = []
    for i in range(12):
        img = np.full((64, 96, 3), 40, np.uint8)
        img[:16, :16] = 250  # a marker in the top-left corner
        img[40:48, 8 * i:8 * i + 8] = 200  # a block moving right, one per frame
        frames.append(img)
    write_video(tmp_path / "clip.mp4", frames, fps=60)
    return tmp_path / "clip.mp4"


def test_probe_and_stream(clip):
    info = probe(clip)
    assert (info.width, info.height, info.frame_count, info.rotation_deg) == (96, 64, 12, 0)
    assert info.fps == 60
    frames = list(iter_frames(clip, width=48))
    assert len(frames) == 12 and frames[0].image.shape == (32, 48, 3)
    assert np.isclose(frames[3].time, 3 / 60)
    picked = read_frames(clip, [7, 2])
    assert sorted(picked) == [2, 7]
    # Frame 7's moving block sits at x = 56..63.
    assert picked[7][44, 60].mean() > 150 and picked[2][44, 60].mean() < 100


@pytest.mark.parametrize("rotation, corner", [(90, (-1, 0)), (-90, (0, -1)), (180, (-1, -1))])
def test_display_rotation_is_applied(tmp_path, rotation, corner):
    img = np.zeros((32, 64, 3), np.uint8)
    img[:8, :8] = 255
    write_video(tmp_path / "r.mp4", [img] * 3, rotation=rotation)
    info = probe(tmp_path / "r.mp4")
    up = next(iter_frames(tmp_path / "r.mp4")).image
    assert up.shape[:2] == (info.height, info.width)
    assert up[corner[0] * 3, corner[1] * 3].mean() > 200  # the top-left marker moved there


def test_bad_videos(tmp_path):
    with pytest.raises(InputError, match="not found"):
        probe(tmp_path / "none.mp4")
    (tmp_path / "empty.mp4").write_bytes(b"")
    with pytest.raises(InputError):
        probe(tmp_path / "empty.mp4")
    (tmp_path / "photo.mp4").write_bytes(b"\xff\xd8\xff\xe0" + b"\x00" * 200)
    with pytest.raises(InputError):
        probe(tmp_path / "photo.mp4")


def test_frames_read_ahead_in_their_own_thread_stop_with_their_caller(clip, monkeypatch):
    """The frames are decoded ahead in a thread: the caller gets them all in order, an error
    of the decoding thread is raised in the caller's, and a caller that stops early (a
    ``break``, its own error) leaves no thread behind."""
    import threading

    import facecap_core.video as video

    def alive() -> int:
        return sum(t.name == "frames" and t.is_alive() for t in threading.enumerate())

    assert [f.index for f in iter_frames(clip)] == list(range(12))
    for frame in iter_frames(clip):
        if frame.index == 1:
            break
    assert alive() == 0
    with pytest.raises(ZeroDivisionError):
        for frame in iter_frames(clip):
            1 / (frame.index - 2)
    assert alive() == 0

    decoded = video._decoded

    def broken(path, width, grey, indices):
        yield from list(decoded(path, width, grey, indices))[:3]
        raise InputError(f"{path}: decoding stopped (InvalidDataError); the file is damaged")

    monkeypatch.setattr(video, "_decoded", broken)
    seen = []
    with pytest.raises(InputError, match="decoding stopped"):
        seen.extend(f.index for f in iter_frames(clip))
    assert seen == [0, 1, 2] and alive() == 0
