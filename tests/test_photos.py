"""A folder of photos as a capture: reading, refusals, and poses from photos in any order."""

from __future__ import annotations

import struct
import warnings
import zlib

import numpy as np
import pytest
from PIL import Image
from PIL.TiffImagePlugin import IFDRational

from facecap.tasks.store import input_key
from facecap_core.errors import InputError
from facecap_core.photos import probe_photos, read_photo
from facecap_core.video import iter_frames, probe, read_frames


def _photos(folder, sizes, orientation=None, exif_focal_35mm=None, exif_ifd=None):
    """Random photos of ``sizes``; ``exif_ifd``: tags of their EXIF sub-IFD (0x8769)."""
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    for i, (w, h) in enumerate(sizes):
        image = Image.fromarray(rng.integers(0, 255, (h, w, 3), np.uint8))
        exif = Image.Exif()
        if orientation:
            exif[0x0112] = orientation
        if exif_focal_35mm:
            exif.get_ifd(0x8769)[0xA405] = exif_focal_35mm
        exif.get_ifd(0x8769).update(exif_ifd or {})
        image.save(folder / f"img_{i:03d}.jpg", exif=exif)
    return folder


def png_claiming(path, width: int, height: int):
    """An 8x8 PNG whose header says ``width`` x ``height`` (its IHDR chunk rewritten, the
    chunk's CRC with it): a reader that trusts the header sees a photo of that size."""
    import io

    buffer = io.BytesIO()
    Image.new("L", (8, 8)).save(buffer, "PNG")
    data = bytearray(buffer.getvalue())
    data[16:24] = struct.pack(">II", width, height)  # after the signature, length and type
    data[29:33] = struct.pack(">I", zlib.crc32(bytes(data[12:29])))
    path.write_bytes(bytes(data))
    return path


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


def test_a_png_cut_short_is_named_when_probed(tmp_path):
    """Found by the fuzz test: a PNG's EXIF may follow its pixels, so reading it decodes
    them, and a PNG cut short fails while the folder is probed: in one message."""
    folder = tmp_path / "p"
    folder.mkdir()
    rng = np.random.default_rng(0)
    for i in range(5):
        Image.fromarray(rng.integers(0, 255, (48, 64, 3), np.uint8)).save(folder / f"{i}.png")
    whole = (folder / "2.png").read_bytes()
    (folder / "2.png").write_bytes(whole[: len(whole) // 2])
    with pytest.raises(InputError, match=r"2.png cannot be decoded \(OSError\); the file is "
                                         "damaged or truncated"):
        probe_photos(folder)


def test_a_photo_folder_key_follows_its_content(tmp_path):
    folder = _photos(tmp_path / "p", [(64, 48)] * 5)
    key = input_key(folder)
    assert input_key(_photos(tmp_path / "same", [(64, 48)] * 5)) == key
    (folder / "img_003.jpg").rename(folder / "img_099.jpg")  # same bytes, other order
    assert input_key(folder) != key


FOCAL_TAGS = {0x920A: IFDRational(26, 10), 0xA20E: IFDRational(4000, 1), 0xA210: 2}
"""A 2.6 mm focal length on a sensor of 4000 pixels per inch (FocalLength,
FocalPlaneXResolution, FocalPlaneResolutionUnit 2: inches)."""


@pytest.mark.parametrize("tag", [0x920A, 0xA20E], ids=["FocalLength", "FocalPlaneXResolution"])
def test_an_exif_focal_length_that_is_no_number_is_ignored(tmp_path, tag):
    """A rational of denominator 0 reads as NaN: it is no focal length, and the photos get
    the pose stage's default guess instead, as photos without EXIF do."""
    good = probe_photos(_photos(tmp_path / "good", [(64, 48)] * 5, exif_ifd=FOCAL_TAGS))
    assert good.focal_px == pytest.approx(2.6 * 4000 / 25.4)
    bad = {**FOCAL_TAGS, tag: IFDRational(1, 0)}
    assert probe_photos(_photos(tmp_path / "bad", [(64, 48)] * 5, exif_ifd=bad)).focal_px is None
    # A photo with the broken tag among good ones: the good ones give the focal length.
    mixed = _photos(tmp_path / "mixed", [(64, 48)] * 5, exif_ifd=FOCAL_TAGS)
    _photos(tmp_path / "one", [(64, 48)], exif_ifd=bad)
    (tmp_path / "one" / "img_000.jpg").replace(mixed / "img_002.jpg")
    assert probe_photos(mixed).focal_px == pytest.approx(good.focal_px)


def test_a_photo_over_the_size_limit_is_refused_from_its_header(tmp_path):
    """A header that says 100000x100000 (Pillow's decompression-bomb error) or a real
    8000x12000 photo (96 megapixels: Pillow's warning) is refused in one message naming
    the photo, its size and the limit (FACECAP_MAX_SIDE_PX), without a warning."""
    folder = _photos(tmp_path / "p", [(64, 48)] * 4)
    png_claiming(folder / "img_huge.png", 100_000, 100_000)
    with pytest.raises(InputError, match=r"img_huge.png is 100000x100000 pixels, larger than "
                                         r"the limit of 8192 on the long side; give photos"):
        probe_photos(folder)
    (folder / "img_huge.png").unlink()
    Image.new("1", (8000, 12000)).save(folder / "img_big.png")  # 12 kB: one colour
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        for read in (probe_photos, lambda f: read_photo(f / "img_big.png")):
            with pytest.raises(InputError, match="img_big.png is 8000x12000 pixels"):
                read(folder)
    assert [str(w.message) for w in seen] == []


def test_pillow_warnings_about_a_photo_are_not_shown(tmp_path):
    """A photo Pillow warns about (a palette PNG whose transparency is given per entry) is
    read without a warning: what is wrong with a photo is said in one line, or not at all."""
    image = Image.new("P", (64, 48))
    image.putpalette([0, 0, 0, 255, 0, 0] * 128)
    image.save(tmp_path / "palette.png", transparency=bytes([0, 255] * 128))
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        assert read_photo(tmp_path / "palette.png", grey=True).shape == (48, 64)
    assert [str(w.message) for w in seen] == []


def test_empty_frame_list_reads_nothing_from_a_video(tmp_path):
    from tests.media import write_video

    video = write_video(tmp_path / "v.mp4", [np.zeros((32, 48, 3), np.uint8)] * 3)
    assert list(iter_frames(video, indices=[])) == []
    assert read_frames(video, []) == {}


@pytest.mark.slow
def test_shuffled_photos_get_every_camera_in_sweep_order(tmp_path, ict4_sweep):
    """Photos of a sweep saved under shuffled names: exhaustive matching registers all, the
    views come out in sweep order, and the cameras are as good as the video's."""
    from facecap.synthetic import load_gt_cameras
    from facecap_core.keyframes import load_keyframes
    from facecap_core.keyframes import main as keyframes_main
    from facecap_core.pose.evaluate import pose_errors
    from facecap_core.pose.stage import PoseConfig, estimate_poses

    capture = ict4_sweep
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
    steps, _ = estimate_poses(folder, kf, tmp_path / "work", PoseConfig(sfm_width=640))
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
