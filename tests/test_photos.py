"""A folder of photos as a capture: reading, refusals, and poses from photos in any order."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from facecap_core.errors import InputError
from facecap_core.photos import probe_photos, read_photo
from facecap_core.video import iter_frames, probe, read_frames
from tasks.store import input_key


def _photos(folder, sizes, orientation=None, exif_focal_35mm=None):
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    for i, (w, h) in enumerate(sizes):
        image = Image.fromarray(rng.integers(0, 255, (h, w, 3), np.uint8))
        exif = Image.Exif()
        if orientation:
            exif[0x0112] = orientation
        if exif_focal_35mm:
            exif.get_ifd(0x8769)[0xA405] = exif_focal_35mm
        image.save(folder / f"img_{i:03d}.jpg", exif=exif)
    return folder


def test_photos_are_frames_in_name_order_turned_upright(tmp_path):
    # EXIF orientation 6: the stored landscape pixels are shown turned 90° clockwise.
    folder = _photos(tmp_path / "p", [(64, 48)] * 6, orientation=6)
    info = probe(folder)
    assert (info.width, info.height, info.frame_count) == (48, 64, 6)
    first = read_photo(folder / "img_000.jpg")
    assert first.shape == (64, 48, 3)
    frames = list(iter_frames(folder, indices=[4, 1]))
    assert [f.index for f in frames] == [1, 4]
    assert read_frames(folder, [3], width=24)[3].shape == (32, 24, 3)
    assert list(iter_frames(folder, indices=[])) == []


def test_exif_35mm_focal_length_becomes_pixels(tmp_path):
    # 26 mm equivalent over the 43.27 mm diagonal of a 36x24 frame, on a 4:3 image.
    folder = _photos(tmp_path / "p", [(400, 300)] * 5, exif_focal_35mm=26)
    info = probe_photos(folder)
    assert info.focal_px == pytest.approx(26 / np.hypot(36, 24) * 500, rel=1e-9)
    assert probe_photos(_photos(tmp_path / "q", [(400, 300)] * 5)).focal_px is None


def test_mixed_sizes_and_too_few_photos_are_refused(tmp_path):
    folder = _photos(tmp_path / "p", [(64, 48)] * 4 + [(48, 64)] * 2)
    with pytest.raises(InputError, match=r"mixes photo sizes \(64x48: 4 .*48x64: 2"):
        probe_photos(folder)
    with pytest.raises(InputError, match="holds 3 photo"):
        probe_photos(_photos(tmp_path / "few", [(64, 48)] * 3))
    (tmp_path / "junk").mkdir()
    (tmp_path / "junk" / "a.jpg").write_bytes(b"not a jpeg")
    for i in range(5):
        (tmp_path / "junk" / f"b{i}.png").write_bytes(b"\x89PNG nope")
    with pytest.raises(InputError, match="not a readable image"):
        probe_photos(tmp_path / "junk")
    # Probing reads headers only; a photo cut short is named when its pixels are read.
    cut = _photos(tmp_path / "cut", [(64, 48)] * 5)
    whole = (cut / "img_002.jpg").read_bytes()
    (cut / "img_002.jpg").write_bytes(whole[: len(whole) // 2])
    assert probe_photos(cut).width == 64
    with pytest.raises(InputError, match="img_002.jpg cannot be decoded.*damaged or truncated"):
        read_photo(cut / "img_002.jpg")


def test_a_photo_folder_key_follows_its_content(tmp_path):
    folder = _photos(tmp_path / "p", [(64, 48)] * 5)
    key = input_key(folder)
    assert input_key(_photos(tmp_path / "same", [(64, 48)] * 5)) == key
    (folder / "img_003.jpg").rename(folder / "img_099.jpg")  # same bytes, other order
    assert input_key(folder) != key


def test_empty_frame_list_reads_nothing_from_a_video(tmp_path):
    from tests.media import write_video

    video = write_video(tmp_path / "v.mp4", [np.zeros((32, 48, 3), np.uint8)] * 3)
    assert list(iter_frames(video, indices=[])) == []
    assert read_frames(video, []) == {}


@pytest.mark.slow
def test_shuffled_photos_get_every_camera_in_sweep_order(tmp_path, ict_model):
    """Photos of a sweep saved under shuffled names: exhaustive matching registers all, the
    views come out in sweep order, and the cameras are as good as the video's."""
    from facecap_core.config import PoseConfig, SynthConfig
    from facecap_core.keyframes import load_keyframes
    from facecap_core.keyframes import main as keyframes_main
    from facecap_core.pose.evaluate import pose_errors
    from facecap_core.pose.stage import estimate_poses
    from facecap_core.synthetic import load_gt_cameras, synthesize

    capture = synthesize(SynthConfig(subject="ict:4", ict_model=ict_model, width=640,
                                     height=360, duration_s=3.0, seed=4),
                         tmp_path / "capture", progress=False)
    taken = np.linspace(0, capture.frames - 1, 30).round().astype(int)
    names = np.random.default_rng(1).permutation(len(taken))
    folder = tmp_path / "photos"
    folder.mkdir()
    frames = read_frames(capture.video, taken)
    for name, index in zip(names, taken):
        Image.fromarray(frames[index]).save(folder / f"IMG_{name:04d}.jpg", quality=95)
    video_index = {int(name): int(index) for name, index in zip(names, taken)}

    kf = load_keyframes(keyframes_main(folder, tmp_path / "kf"))
    assert kf.ordered is False and kf.indices == list(range(len(taken)))
    steps = estimate_poses(folder, kf, tmp_path / "work", PoseConfig(sfm_width=640))
    final = steps["pba"]
    assert sorted(final.frame_indices) == kf.indices  # every photo registered
    order = [video_index[i] for i in final.frame_indices]
    assert order in (sorted(order), sorted(order, reverse=True))  # a sweep, either way
    intr_gt, gt = load_gt_cameras(capture.gt_cameras)
    err = pose_errors(final.R, final.t, final.intrinsics, [gt[i]["R"] for i in order],
                      [gt[i]["t"] for i in order], intr_gt)
    # COLMAP's accuracy on 30 views (no LK tracks between photos, so the principal point
    # stays at the image centre, 6 px from the rendered one: rotations tilt to make up).
    assert err["rotation_deg"] < 1.0 and err["centre_pct"] < 0.5 and err["focal_pct"] < 3.0


def test_heic_photos_are_read_upright(tmp_path):
    from pillow_heif import register_heif_opener

    register_heif_opener()
    folder = tmp_path / "heic"
    folder.mkdir()
    rng = np.random.default_rng(0)
    for i in range(5):
        Image.fromarray(rng.integers(0, 255, (40, 64, 3), np.uint8)).save(
            folder / f"IMG_{i}.HEIC", quality=90)
    info = probe(folder)
    assert (info.width, info.height, info.frame_count) == (64, 40, 5)
    assert read_frames(folder, [2])[2].shape == (40, 64, 3)
