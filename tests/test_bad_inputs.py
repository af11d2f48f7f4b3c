"""The bad-input corpus, through the ``facecap`` command line.

One module on purpose (~800 lines): the corpus is one table of inputs and the words their
refusal must contain, read and extended in one place (docs/robustness.md mirrors it).

Every input below is generated on the fly (tiny videos of a cheap 3D scene: coloured dots on a
head-sized blob in front of a wall, filmed by an orbiting camera) and given to ``facecap`` as a
user would. A refused input must end with exit code 2 and exactly one stderr line
``facecap: error: <what is wrong>; <what to do>``, no traceback, and nothing that was already
in the artifact store or the output folder removed or changed. Inputs a phone legitimately
produces (240 fps, portrait rotation, a variable frame rate, 8K, odd folder names) are accepted
instead, and the test checks that they are handled right.

Most refusals happen in the preflight checks (``flows.capture.preflight``), before a Prefect
server is needed; the few only a stage can see (a static camera, no face, a full disk) run the
real flow on one Prefect test server shared by the module. :data:`CORPUS` maps each input to
the words its message must contain (docs/robustness.md lists the messages).
"""

from __future__ import annotations

import errno
import hashlib
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import av
import cv2
import numpy as np
import pytest

from facecap.cli import main
from facecap.tasks.store import ArtifactStore, artifact_key, open_store
from facecap_core.camera import look_at
from tests.media import write_video
from tests.test_photos import png_claiming

ROOT = Path(__file__).resolve().parents[1]
W, H = 224, 128  # the smallest 16:9 size above the preflight's 120-pixel floor


# --------------------------------------------------------------------------- media


def orbit_frames(n: int, yaw_deg=(-40.0, 40.0), width: int = W, height: int = H,
                 seed: int = 0) -> list[np.ndarray]:
    """A camera circling a head-sized blob of coloured dots in front of a wall: real
    parallax for the keyframe tracker and the pose stage, and no face."""
    rng = np.random.default_rng(seed)
    blob = rng.normal(size=(700, 3))
    blob *= rng.uniform(70, 100, (700, 1)) / np.linalg.norm(blob, axis=1, keepdims=True)
    wall = np.column_stack([rng.uniform(-600, 600, 1100), rng.uniform(-400, 400, 1100),
                            np.full(1100, -500.0)])
    points = np.vstack([blob, wall])
    colours = rng.integers(30, 255, (len(points), 3)).tolist()
    f, cx, cy = 0.9 * width, (width - 1) / 2, (height - 1) / 2
    frames = []
    for yaw in np.radians(np.linspace(*yaw_deg, n)):
        R, t = look_at(450 * np.array([np.sin(yaw), 0.0, np.cos(yaw)]), np.zeros(3),
                       np.array([0.0, -1.0, 0.0]))
        cam = points @ R.T + t
        image = np.full((height, width, 3), 90, np.uint8)
        for i in np.argsort(-cam[:, 2]):  # far to near
            x, y, z = cam[i]
            u, v = f * x / z + cx, f * y / z + cy
            if -4 < u < width + 4 and -4 < v < height + 4:
                cv2.circle(image, (int(u * 4), int(v * 4)), 4 * max(1, round(900 / z)),
                           colours[i], -1, cv2.LINE_AA, shift=2)
        frames.append(image)
    return frames


def _mux_silence(container, stream) -> None:
    """Half a second of silence into an AAC stream."""
    for i in range(20):
        frame = av.AudioFrame.from_ndarray(np.zeros((1, 1024), np.float32), format="fltp",
                                           layout="mono")
        frame.sample_rate, frame.pts = 44100, i * 1024
        for packet in stream.encode(frame):
            container.mux(packet)
    for packet in stream.encode():
        container.mux(packet)


def write_audio_only(path: Path) -> Path:
    with av.open(str(path), "w", format="mp4") as container:
        _mux_silence(container, container.add_stream("aac", rate=44100))
    return path


def write_empty_video_track(path: Path, format: str = "matroska", options=None) -> Path:
    """A file whose video track holds no frame (its audio does)."""
    with av.open(str(path), "w", format=format, options=options or {}) as container:
        video = container.add_stream("libx264", rate=30)
        video.width, video.height, video.pix_fmt = W, H, "yuv420p"
        _mux_silence(container, container.add_stream("aac", rate=44100))
    return path


def write_streams(path: Path, streams: list[list[np.ndarray]], format: str = "mp4") -> Path:
    """One file holding each list of frames as a video stream of its own, in order."""
    with av.open(str(path), "w", format=format) as container:
        added = []
        for frames in streams:  # every stream before the first packet
            added.append(container.add_stream("libx264", rate=30))
            added[-1].height, added[-1].width = frames[0].shape[:2]
            added[-1].pix_fmt = "yuv420p"
        for stream, frames in zip(added, streams):
            for i, image in enumerate(frames):
                frame = av.VideoFrame.from_ndarray(image, format="rgb24")
                frame.pts = i
                for packet in stream.encode(frame):
                    container.mux(packet)
            for packet in stream.encode():
                container.mux(packet)
    return path


def write_resolution_change(path: Path, first: list[np.ndarray], then: list[np.ndarray]
                            ) -> Path:
    """One H.264 stream whose frames change size midway: two MPEG-TS recordings spliced
    (as ``cat a.ts b.ts`` does), which decoders play through."""
    parts = [write_streams(path.with_suffix(f".{i}.ts"), [frames], format="mpegts")
             for i, frames in enumerate((first, then))]
    path.write_bytes(b"".join(p.read_bytes() for p in parts))
    return path


VFR_TIMES = np.cumsum(np.r_[0.0, np.where(np.arange(39) % 3 == 0, 0.050, 0.021)])
"""Frame times of the variable-frame-rate video: gaps of 21 and 50 ms."""


@pytest.fixture(scope="module")
def media(tmp_path_factory) -> dict[str, Path]:
    """Every corpus video, written once (about 5 s of CPU)."""
    d = tmp_path_factory.mktemp("media")
    orbit = orbit_frames(40)
    m = {"orbit": write_video(d / "orbit.mp4", orbit)}
    m["static"] = write_video(d / "static.mp4", orbit_frames(20, yaw_deg=(0.0, 0.0)))
    m["still"] = write_video(d / "still.mp4", orbit[:1] * 40)  # one frame, 40 times
    m["frontal"] = write_video(d / "frontal.mp4", orbit_frames(20, yaw_deg=(-3.0, 3.0)))
    (d / "empty.mp4").write_bytes(b"")
    m["empty"] = d / "empty.mp4"
    whole = write_video(d / "whole.mp4", orbit[:30]).read_bytes()  # index (moov) at the end
    (d / "truncated.mp4").write_bytes(whole[: len(whole) // 2])
    m["truncated"] = d / "truncated.mp4"
    first = write_video(d / "indexed.mp4", orbit[:30], faststart=True).read_bytes()
    (d / "truncated_indexed.mp4").write_bytes(first[: len(first) // 2])
    m["truncated_indexed"] = d / "truncated_indexed.mp4"
    ok, jpeg = cv2.imencode(".jpg", orbit[0])
    (d / "photo.mp4").write_bytes(jpeg.tobytes())
    m["photo"] = d / "photo.mp4"
    m["audio"] = write_audio_only(d / "audio.mp4")
    m["three_frames"] = write_video(d / "three.mp4", orbit[:3])
    m["tiny"] = write_video(d / "tiny.mp4", [cv2.resize(f, (64, 64)) for f in orbit[:20]])
    m["fps240"] = write_video(d / "fast.mp4", orbit, fps=240)
    m["portrait"] = write_video(d / "portrait.mp4", orbit, rotation=90)
    m["vfr"] = write_video(d / "vfr.mp4", orbit, times=VFR_TIMES)
    texture = cv2.resize(orbit[0], (7680, 4320), interpolation=cv2.INTER_NEAREST)
    m["8k"] = write_video(d / "8k.mp4", [texture, texture], codec="mpeg4")
    m["rot45"] = write_video(d / "rot45.mp4", orbit, rotation=45)
    m["empty_track"] = write_empty_video_track(d / "empty track.mkv")
    # A fragmented MP4 keeps the empty track in its header (a plain MP4 drops it).
    m["empty_track_mp4"] = write_empty_video_track(
        d / "empty track.mp4", "mp4", {"movflags": "frag_keyframe+empty_moov"})
    preview = [cv2.resize(orbit[0], (W // 2, H // 2))]  # a one-frame preview first
    m["two_streams"] = write_streams(d / "two streams.mp4", [preview, orbit])
    m["resolution_change"] = write_resolution_change(
        d / "spliced.mp4", orbit[:20], orbit_frames(20, width=320, height=180))
    black = np.zeros((4752, 8448, 3), np.uint8)
    m["over_8k"] = write_video(d / "9k.mp4", [black, black], codec="mjpeg")
    return m


# --------------------------------------------------------------------------- what is kept


@pytest.fixture
def home(tmp_path, monkeypatch) -> Path:
    """A FACECAP_HOME of the test's own, holding a copy of the template assets."""
    from facecap_core import assets

    source = assets.menpo3d_data()
    home = tmp_path / "home"
    shutil.copytree(source, home / "assets" / source.name)
    monkeypatch.setenv("FACECAP_HOME", str(home))
    return home


@pytest.fixture
def kept(tmp_path, home) -> dict[str, Path]:
    """A store and an output folder that already hold results of an earlier run."""
    store_dir, out = tmp_path / "store", tmp_path / "out"
    store = open_store(store_dir)
    key = artifact_key("fitting", {"fusion": "fusion-" + "0" * 32}, {"a": 1}, "1")
    store.put(key, {"mesh.ply": b"ply of an earlier run", "fit.json": b"{}"}, stage="fitting",
              inputs={"fusion": "fusion-" + "0" * 32}, config={"a": 1}, version="1")
    out.mkdir()
    (out / "mesh.ply").write_bytes(b"mesh of an earlier run")
    (out / "report.json").write_text(json.dumps({"earlier": True}))
    return {"store": store_dir, "out": out}


def snapshot(*folders: Path) -> dict[str, str]:
    """sha256 of every file under the folders (the store's committed artifacts only)."""
    files = {}
    for folder in folders:
        root = folder / "artifacts" if (folder / "artifacts").is_dir() else folder
        for path in sorted(root.rglob("*")):
            if path.is_file():
                files[str(path)] = hashlib.sha256(path.read_bytes()).hexdigest()
    return files


def assert_kept(before: dict[str, str], after: dict[str, str]) -> None:
    assert {p: after.get(p) for p in before} == before, "an earlier result was removed or changed"


def assert_one_line_error(code: int, err: str, expected: list[str]) -> str:
    assert code == 2, err
    assert "Traceback" not in err, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("facecap: error: "), err
    for word in expected:
        assert word.lower() in lines[0].lower(), (word, lines[0])
    return lines[0]


def facecap(capfd, *argv) -> tuple[int, str, str]:
    """``facecap ARGV`` in this process; output captured at the file descriptors, so that
    whatever Prefect's log handlers print is seen too."""
    code = main([str(a) for a in argv])
    out, err = capfd.readouterr()
    return code, out, err


# --------------------------------------------------------------------------- the corpus


def _copy(source: Path, target: Path) -> Path:
    target.parent.mkdir(parents=True, exist_ok=True)
    target.write_bytes(source.read_bytes())
    return target


def _config_bytes(tmp: Path, data: bytes) -> Path:
    (tmp / "pipeline.yaml").write_bytes(data)
    return tmp / "pipeline.yaml"


def _config(tmp: Path, text: str, name: str = "pipeline.yaml") -> Path:
    tmp.mkdir(parents=True, exist_ok=True)
    (tmp / name).write_text(text)
    return tmp / name


def _reconstruct_with(config_text: str):
    """The command line of a reconstruction of the orbit capture with ``config_text`` as its
    settings file (a case of :data:`CORPUS`)."""
    return lambda m, t, k: ["reconstruct", m["orbit"], "--config", _config(t, config_text)]


def _scan(tmp: Path) -> Path:
    (tmp / "scan.ply").write_text("ply\nformat ascii 1.0\nelement vertex 0\nend_header\n")
    return tmp / "scan.ply"


def _corrupt_template(tmp: Path) -> None:
    template = Path(os.environ["FACECAP_HOME"]) / "assets" / "menpo3d-0.8.6" / "template.ply"
    data = bytearray(template.read_bytes())
    data[len(data) // 2] ^= 0xFF  # one flipped byte: still parses, silently wrong
    template.write_bytes(bytes(data))


def _output_is_a_file(tmp: Path) -> Path:
    (tmp / "results").write_text("a file where the output folder should be")
    return tmp / "results"


def _dataset_with_escaping_link(tmp: Path) -> Path:
    outside = tmp / "elsewhere" / "subject"
    outside.mkdir(parents=True)
    (outside / "take.mp4").write_bytes(b"")
    root = tmp / "dataset"
    root.mkdir()
    (root / "escape").symlink_to(outside, target_is_directory=True)
    return root


def _a_file(tmp: Path) -> Path:
    (tmp / "store.tar").write_text("a file where the store's folder should be")
    return tmp / "store.tar"


def _a_link_loop(tmp: Path) -> Path:
    (tmp / "store.loop").symlink_to(tmp / "store.loop")
    return tmp / "store.loop"


def _a_dangling_link(tmp: Path) -> Path:
    (tmp / "nowhere").symlink_to(tmp / "gone")
    return tmp / "nowhere"


def _dataset_with_a_subject_named(tmp: Path, subject: str, video: Path) -> Path:
    _copy(video, tmp / "dataset" / subject / "take.mp4")
    return tmp / "dataset"


def _dataset_with_two_takes_of_one_name(tmp: Path, video: Path) -> Path:
    _copy(video, tmp / "dataset" / "anna" / "take.mp4")
    _copy(video, tmp / "dataset" / "anna" / "take.mov")
    return tmp / "dataset"


def _damaged_evaluation_history(out: Path) -> Path:
    (out / "evaluations").mkdir(parents=True, exist_ok=True)
    (out / "evaluations" / "20260101T000000000000Z.json").write_text('{"captures": [1, 2]}')
    return out


def _dataset_without_captures(tmp: Path) -> Path:
    (tmp / "dataset" / "subject a").mkdir(parents=True)
    (tmp / "dataset" / "subject a" / "notes.txt").write_text("no video here")
    return tmp / "dataset"


def _photo_folder(tmp: Path) -> Path:
    """Five W x H photos, IMG_0.jpg to IMG_4.jpg, in ``tmp/photos of anna``."""
    folder = tmp / "photos of anna"
    folder.mkdir(parents=True)
    rng = np.random.default_rng(0)
    for i in range(5):
        cv2.imwrite(str(folder / f"IMG_{i}.jpg"), rng.integers(0, 255, (H, W, 3), np.uint8))
    return folder


def _photos_with_png_claiming(tmp: Path, width: int, height: int) -> Path:
    """The photo folder with IMG_2.jpg replaced by a tiny PNG whose header says
    ``width`` x ``height``."""
    folder = _photo_folder(tmp)
    (folder / "IMG_2.jpg").unlink()
    png_claiming(folder / "IMG_2.png", width, height)
    return folder


def _photos_with_a_large_png(tmp: Path) -> Path:
    """The photo folder with IMG_2.jpg replaced by a real 8000x12000 PNG (96 megapixels,
    over Pillow's warning threshold of 89; one colour, so 12 kB)."""
    from PIL import Image

    folder = _photo_folder(tmp)
    (folder / "IMG_2.jpg").unlink()
    Image.new("1", (8000, 12000)).save(folder / "IMG_2.png")
    return folder


def _photos_with_a_truncated_one(tmp: Path) -> Path:
    """The photo folder with IMG_2.jpg cut in half: its header reads, its pixels do not."""
    folder = _photo_folder(tmp)
    whole = (folder / "IMG_2.jpg").read_bytes()
    (folder / "IMG_2.jpg").write_bytes(whole[: len(whole) // 2])
    return folder


def _a_folder(tmp: Path) -> Path:
    (tmp / "pipeline.yaml").mkdir()
    return tmp / "pipeline.yaml"


def _a_fifo(tmp: Path) -> Path:
    os.mkfifo(tmp / "pipeline.yaml")  # opening it to read would wait for a writer
    return tmp / "pipeline.yaml"


ICT_SUBJECT_FORMS = ["names no subject", "ict:seed with seed a whole number from 0 to 4294967295",
                     "ict:mean, james, or the path of a mesh file"]


CORPUS = {
    # name: (argv builder (media, tmp, kept) -> facecap arguments, words the message holds)
    "missing video": (lambda m, t, k: ["reconstruct", t / "nope.mp4"], ["capture not found"]),
    "a video named by 300 characters (ENAMETOOLONG)": (
        lambda m, t, k: ["reconstruct", t / ("a" * 300 + ".mp4")],
        ["is 304 bytes long, longer than a file or folder name can be (255)",
         "give a shorter name"]),
    "dataset: a folder named by 300 characters": (
        lambda m, t, k: ["dataset", t / ("d" * 300), "--out", k["out"]],
        ["is 300 bytes long, longer than a file or folder name can be (255)"]),
    "empty file": (lambda m, t, k: ["reconstruct", m["empty"]],
                   ["not a readable video", "give an mp4"]),
    "truncated MP4, index at the end": (lambda m, t, k: ["reconstruct", m["truncated"]],
                                        ["not a readable video", "give an mp4"]),
    "truncated MP4, index first": (lambda m, t, k: ["reconstruct", m["truncated_indexed"]],
                                   ["truncated", "of its 30 frames", "copy the whole file"]),
    "JPEG renamed .mp4": (lambda m, t, k: ["reconstruct", m["photo"]],
                          ["single image (mjpeg)", "not a video", "give the capture"]),
    "audio-only file": (lambda m, t, k: ["reconstruct", m["audio"]],
                        ["no video stream", "give a video file"]),
    "3-frame video": (lambda m, t, k: ["reconstruct", m["three_frames"]],
                      ["has 3 frames", "at least 15", "record a slow sweep"]),
    "64x64 video": (lambda m, t, k: ["reconstruct", m["tiny"]],
                    ["64x64 pixels", "too small", "record at least 120"]),
    "larger than 8K (8448x4752)": (lambda m, t, k: ["reconstruct", m["over_8k"]],
                                   ["8448x4752", "larger than the limit of 8192",
                                    "record at 8k or less"]),
    "config: NaN": (_reconstruct_with("mvs: {depth: {sigma_color: .nan}}\n"),
                    ["mvs.depth.sigma_color", "finite number", "correct or remove"]),
    "config: NaN in a list": (_reconstruct_with("fitting: {stiffness: [.nan, 1]}\n"),
                              ["fitting.stiffness.0", "finite number"]),
    "config: infinity": (_reconstruct_with("coarse: {rbf_kernel_mm: .inf}\n"),
                         ["coarse.rbf_kernel_mm", "finite number"]),
    "config: negative value": (_reconstruct_with("mvs: {depth: {iterations: -3}}\n"),
                               ["mvs.depth.iterations", "greater than or equal to 1"]),
    "config: unknown key": (_reconstruct_with("fitting: {stifness: [1.0]}\n"),
                            ["fitting.stifness", "extra inputs are not permitted",
                             "correct or remove"]),
    "a capture named like a result in --out": (
        lambda m, t, k: ["reconstruct", _copy(m["orbit"], t / "results" / "report.json"),
                         "--out", t / "results"], ["report.json would be overwritten",
                                                    "another --out"]),
    "a config named like a result in --out": (
        lambda m, t, k: ["reconstruct", m["orbit"], "--config",
                         _config(t / "results", "{}\n", "coarse.json"), "--out", t / "results"],
        ["config", "coarse.json would be overwritten", "another --out"]),
    "an IPD no adult has": (lambda m, t, k: ["reconstruct", m["orbit"], "--ipd-mm", "6.3"],
                            ["--ipd-mm", "ipd_mm", "greater than or equal to 40"]),
    "config: unknown section": (_reconstruct_with("meshing: {depth: 9}\n"),
                                ["meshing", "extra inputs"]),
    "config: not YAML": (_reconstruct_with("mvs: {iterations: [\n"),
                         ["not valid yaml"]),
    "config: not a mapping": (_reconstruct_with("- mvs\n- fitting\n"),
                              ["must hold a mapping"]),
    "config: Latin-1": (lambda m, t, k: ["reconstruct", m["orbit"], "--config",
                                         _config_bytes(t, b"mvs: {depth: {iterations: 4}} # caf\xe9\n")],
                        ["not UTF-8", "save it as UTF-8"]),
    "config: UTF-16": (lambda m, t, k: ["reconstruct", m["orbit"], "--config",
                                        _config_bytes(t, "mvs: {depth: {iterations: 4}}\n".encode("utf-16"))],
                       ["not UTF-8"]),
    "config: nested 20,000 deep": (lambda m, t, k: ["reconstruct", m["orbit"], "--config",
                                                    _config(t, "a: " + "[" * 20000 + "]" * 20000)],
                                   ["nests too deeply"]),
    "config: an empty list": (_reconstruct_with("[]\n"), ["must hold a mapping"]),
    "config: false": (_reconstruct_with("false\n"), ["must hold a mapping"]),
    "config file missing": (lambda m, t, k: ["reconstruct", m["orbit"], "--config",
                                             t / "none.yaml"], ["config file not found"]),
    "scan without landmarks": (lambda m, t, k: ["reconstruct", m["orbit"], "--scan", _scan(t)],
                               ["needs its 68 3d landmarks", "--scan-landmarks"]),
    "corrupt template": (lambda m, t, k: (_corrupt_template(t), ["reconstruct", m["orbit"]])[1],
                         ["template.ply is damaged", "delete", "facecap assets"]),
    "output folder is a file": (lambda m, t, k: ["reconstruct", m["orbit"], "--out",
                                                 _output_is_a_file(t)],
                                ["output folder", "is a file", "give the path of a folder"]),
    "dataset: a link out of the root": (lambda m, t, k: ["dataset", _dataset_with_escaping_link(t),
                                                         "--out", k["out"]],
                                        ["lies outside the dataset folder", "remove the link"]),
    "dataset: no captures": (lambda m, t, k: ["dataset", _dataset_without_captures(t),
                                              "--out", k["out"]],
                             ["no captures in", "<subject>/<capture>.mp4"]),
    "dataset folder missing": (lambda m, t, k: ["dataset", t / "nowhere", "--out", k["out"]],
                               ["dataset folder not found"]),
    "video: turned by 45° in its metadata": (lambda m, t, k: ["reconstruct", m["rot45"]],
                                             ["rot45.mp4 is to be shown turned by 45°",
                                              "export it upright"]),
    "video: a video track with no frames": (lambda m, t, k: ["reconstruct", m["empty_track"]],
                                            ["has a video track with no frames",
                                             "give the capture's video file"]),
    "video: an MP4 whose video track has no frames": (
        lambda m, t, k: ["reconstruct", m["empty_track_mp4"]],
        ["empty track.mp4 has a video track with no frames", "give the capture's video file"]),
    "store: a file": (lambda m, t, k: ["reconstruct", m["orbit"], "--store", _a_file(t)],
                      ["is not a folder", "is a file", "--store"]),
    "store: a folder inside a file": (lambda m, t, k: ["reconstruct", m["orbit"], "--store",
                                                       _a_file(t) / "artifacts"],
                                      ["artifacts is not a folder", "store.tar is a file"]),
    "store: a link that leads back to itself": (
        lambda m, t, k: ["reconstruct", m["orbit"], "--store", _a_link_loop(t)],
        ["store.loop is not a folder", "a link that leads back to itself", "--store"]),
    "store: a link to nothing": (
        lambda m, t, k: ["reconstruct", m["orbit"], "--store", _a_dangling_link(t) / "store"],
        ["nowhere is a link to nothing", "--store"]),
    "store: an unknown protocol": (lambda m, t, k: ["reconstruct", m["orbit"], "--store",
                                                    "foo://bucket/x"],
                                   ["protocol 'foo'", "give a folder or an s3://"]),
    "store: an HTTP URL (a request to an internal API)": (
        lambda m, t, k: ["reconstruct", m["orbit"], "--store", "http://127.0.0.1:8765/internal/api"],
        ["protocol 'http'", "cannot hold artifacts"]),
    "store: a chained URL (the chained protocols would go unchecked)": (
        lambda m, t, k: ["reconstruct", m["orbit"], "--store", f"simplecache::{t / 'chained'}"],
        ["chains protocols (::)", "give a folder or an s3://"]),
    "dataset: a subject named dataset.json": (
        lambda m, t, k: ["dataset", _dataset_with_a_subject_named(t, "dataset.json", m["orbit"]),
                         "--out", k["out"]], ["dataset.json is named like the summary",
                                              "rename the subject folder"]),
    "dataset: take.mp4 and take.mov of one subject": (
        lambda m, t, k: ["dataset", _dataset_with_two_takes_of_one_name(t, m["orbit"]),
                         "--out", k["out"]], ["take.mov", "are both capture 'take'", "rename one"]),
    "evaluate-dataset: a damaged evaluation in OUT/evaluations": (
        lambda m, t, k: ["evaluate-dataset", _dataset_with_a_subject_named(t, "anna", m["orbit"]),
                         "--out", _damaged_evaluation_history(k["out"])],
        ["20260101T000000000000Z.json is not an evaluation facecap wrote", "move it out"]),
    "config: min_frames 10^30": (lambda m, t, k: ["reconstruct", m["orbit"], "--config",
                                                  _config(t, f"keyframes: {{min_frames: {10**30}}}\n")],
                                 ["keyframes.min_frames", "less than or equal to 100000"]),
    "config: 40 stiffness levels": (
        lambda m, t, k: ["reconstruct", m["orbit"], "--config",
                         _config(t, f"fitting: {{stiffness: {[1.0] * 40}, landmark_weight: "
                                    f"{[1.0] * 40}}}\n")],
        ["fitting.stiffness", "at most 32 items"]),
    "config: a blur no image can take": (
        _reconstruct_with("fitting: {edge_blur_sigma: 1.0e308}\n"),
        ["fitting.edge_blur_sigma", "less than or equal to 20"]),
    "config: weights the solver cannot hold": (
        _reconstruct_with("fitting: {gamma: 1.0e308, data_weight: 1.0e-308}\n"),
        ["fitting.gamma", "less than or equal to 1000"]),
    "config: stiffness and landmark weight 616 orders apart": (
        _reconstruct_with("fitting: {stiffness: [1.0e-308], "
                                    "landmark_weight: [1.0e308]}\n"),
        ["stiffness must lie in [0.001, 10000]", "landmark_weight in [0, 10000]"]),
    "config: a depth search on a level the pyramid lacks": (
        _reconstruct_with("poses: {pba: {points_from_sparse: false, search_level: 3}}\n"),
        ["poses.pba", "search_level (3) must be a level of the pyramid"]),
    "config: 200,000 stiffness levels": (
        lambda m, t, k: ["reconstruct", m["orbit"], "--config",
                         _config(t, f"fitting: {{stiffness: {[1] * 200_000}}}\n")],
        ["too large to be a config", "settings that differ from the defaults"]),
    "photos: a PNG whose header says 100000x100000": (
        lambda m, t, k: ["reconstruct", _photos_with_png_claiming(t, 100_000, 100_000)],
        ["photos of anna/img_2.png is 100000x100000 pixels", "larger than the limit of 8192 on "
         "the long side", "give photos of 8192 pixels or less"]),
    "photos: an 8000x12000 PNG (Pillow would warn)": (
        lambda m, t, k: ["reconstruct", _photos_with_a_large_png(t)],
        ["img_2.png is 8000x12000 pixels", "larger than the limit of 8192"]),
    "config: a folder": (lambda m, t, k: ["reconstruct", m["orbit"], "--config", _a_folder(t)],
                         ["pipeline.yaml is a folder, not a file", "give the path of a yaml file"]),
    "config: a FIFO": (lambda m, t, k: ["reconstruct", m["orbit"], "--config", _a_fifo(t)],
                       ["pipeline.yaml is not a regular file", "give the path of a yaml file"]),
    "config: a key given twice": (
        _reconstruct_with("mvs: {depth: {iterations: 3, iterations: 4}}\n"),
        ["sets mvs.depth.iterations twice", "line 1", "keep one of them"]),
    "config: true for a number": (
        _reconstruct_with("mvs: {depth: {iterations: true}}\n"),
        ["mvs.depth.iterations", "should be a number, not a boolean"]),
    "config: on in a list of numbers": (
        _reconstruct_with("fitting: {stiffness: [1.0, on]}\n"),
        ["fitting.stiffness", "not a boolean"]),
    "config: 1:30 (YAML 1.1 reads base 60: 90)": (
        _reconstruct_with("mvs: {depth: {iterations: 1:30}}\n"),
        ["mvs.depth.iterations", "valid integer"]),
    "config: ._ (a float to a careless resolver)": (
        _reconstruct_with("mvs: {depth: {iterations: ._}}\n"),
        ["mvs.depth.iterations", "valid integer"]),
    "synth: subject ict:-1": (lambda m, t, k: ["synth", "--subject", "ict:-1"],
                              ["subject: 'ict:-1'", *ICT_SUBJECT_FORMS]),
    "synth: subject ict:abc": (lambda m, t, k: ["synth", "--subject", "ict:abc"],
                               ["subject: 'ict:abc'", *ICT_SUBJECT_FORMS]),
    "synth: a config that sets fps twice": (
        lambda m, t, k: ["synth", "--config", _config(t, "fps: 30\nfps: 60\n")],
        ["sets fps twice (the second time on line 2)"]),
    "synth: a config with yes for a number": (
        lambda m, t, k: ["synth", "--config", _config(t, "duration_s: yes\n")],
        ["duration_s", "not a boolean"]),
}


def _with_defaults(argv: list, kept: dict[str, Path]) -> list:
    """``--out`` and ``--store`` of the kept results unless the case gives its own."""
    argv = list(argv)
    if "--out" not in argv:
        argv += ["--out", kept["out"]]
    if argv[0] == "reconstruct" and "--store" not in argv:
        argv += ["--store", kept["store"]]
    return argv


@pytest.mark.parametrize("case", list(CORPUS))
def test_refused_before_anything_runs(case, media, kept, tmp_path, capfd):
    build, expected = CORPUS[case]
    argv = _with_defaults(build(media, tmp_path, kept), kept)
    before = snapshot(kept["store"], kept["out"])
    code, out, err = facecap(capfd, *argv)
    assert_one_line_error(code, err, expected)
    assert_kept(before, snapshot(kept["store"], kept["out"]))


def test_read_only_output_folder(media, kept, tmp_path):
    """A real permission failure: root ignores file modes, so as root the command runs
    without the capability that lets it (CAP_DAC_OVERRIDE)."""
    os.chmod(kept["out"], 0o555)
    try:
        prefix = bound_by_file_modes()
        before = snapshot(kept["store"], kept["out"])
        proc = subprocess.run(
            [*prefix, sys.executable, "-m", "facecap", "reconstruct", str(media["orbit"]),
             "--out", str(kept["out"]), "--store", str(kept["store"])],
            capture_output=True, text=True, cwd=ROOT, timeout=300)
        assert_one_line_error(proc.returncode, proc.stderr,
                              ["cannot write to the output folder", "permission denied",
                               "choose a writable folder"])
        assert_kept(before, snapshot(kept["store"], kept["out"]))
    finally:
        os.chmod(kept["out"], 0o755)


def test_an_oversized_photo_is_one_line_without_pillow_warnings(kept, tmp_path):
    """The promise on the console itself (pytest's own capture keeps warnings off stderr):
    a 96-megapixel photo, which Pillow warns about, is one line in a process of its own."""
    proc = subprocess.run([sys.executable, "-m", "facecap", "reconstruct",
                           str(_photos_with_a_large_png(tmp_path)), "--out", str(kept["out"]),
                           "--store", str(kept["store"])],
                          capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert_one_line_error(proc.returncode, proc.stderr, ["img_2.png is 8000x12000 pixels"])


def test_a_damaged_photo_is_named_as_the_user_gave_it(tmp_path):
    """The stages read a photo folder from the store's copy (``input-<key>/photos/``), so a
    photo that does not decode is refused there under its stored path; the message names
    the user's photo instead (the IN_A_FLOW case shows it through the command)."""
    from facecap.flows.capture import as_user_sees_it
    from facecap.tasks.graph import PHOTOS
    from facecap.tasks.runner import ingest
    from facecap_core.errors import InputError
    from facecap_core.video import iter_frames

    folder = _photos_with_a_truncated_one(tmp_path)
    key = ingest(str(tmp_path / "store"), folder, PHOTOS)
    stored = open_store(tmp_path / "store").get(key) / PHOTOS
    with pytest.raises(InputError) as refused:
        list(iter_frames(stored, grey=True))
    assert f"{key}/{PHOTOS}/IMG_2.jpg cannot be decoded" in str(refused.value)
    line = as_user_sees_it(str(refused.value), folder)
    assert line == (f"{folder / 'IMG_2.jpg'} cannot be decoded (OSError); the file is damaged "
                    "or truncated")


def test_8k_is_accepted_and_streamed_at_processing_width(media, tmp_path):
    """8K passes the preflight checks; the stages read it one frame at a time at their own
    processing width (the 2-frame file needs ``min_frames: 2``)."""
    from facecap.flows.capture import preflight
    from facecap_core.video import iter_frames

    config = _config(tmp_path, "keyframes: {min_frames: 2}\n")
    cfg = preflight(media["8k"], config, out=tmp_path / "out")
    frames = list(iter_frames(media["8k"], width=cfg.keyframes.track_width, grey=True))
    assert [f.image.shape for f in frames] == [(360, 640), (360, 640)]


def test_a_resolution_change_midway_is_refused_by_the_keyframe_stage(media):
    """Two recordings spliced into one stream: the size changes at frame 20. The preflight
    does not decode every frame; the keyframe stage, which does, refuses it in one line
    instead of failing inside OpenCV's tracker."""
    from facecap_core.errors import InputError
    from facecap_core.keyframes import select_keyframes

    with pytest.raises(InputError) as refused:
        select_keyframes(media["resolution_change"])
    assert "spliced.mp4 changes resolution at frame 20 (224x128 to 320x180)" in str(refused.value)
    assert "re-export it at one resolution" in str(refused.value)


def test_a_video_of_one_frame_repeated_is_refused_by_the_keyframe_stage(media):
    """40 identical frames: every tracked point stays where it was, which leaves the
    essential matrix's five-point solver a degenerate polynomial (an OpenCV ``solvePoly``
    assertion, an internal error); the keyframe stage says the camera barely moves."""
    from facecap_core.errors import InputError
    from facecap_core.keyframes import select_keyframes

    with pytest.raises(InputError) as refused:
        select_keyframes(media["still"])
    assert "still.mp4: only 1 keyframe(s) — the camera barely moves" in str(refused.value)
    assert "sweep the phone around the head" in str(refused.value)


def test_the_capture_stream_is_chosen_over_a_preview_stream(media, tmp_path):
    """A file whose first video stream is a one-frame preview: the capture is the stream
    with the frames, in every reader (probe, frame count, decoding)."""
    from facecap.flows.capture import preflight
    from facecap_core.video import iter_frames, probe, stored_frame_count

    preflight(media["two_streams"], out=tmp_path / "out")
    info = probe(media["two_streams"])
    assert (info.width, info.height, info.frame_count) == (W, H, 40)
    assert stored_frame_count(media["two_streams"]) == 40
    assert len(list(iter_frames(media["two_streams"], grey=True))) == 40


def _without_aws_settings(monkeypatch, tmp_path) -> None:
    import s3fs

    for name in [n for n in os.environ if n.startswith(("AWS_", "FSSPEC_S3"))]:
        monkeypatch.delenv(name)
    monkeypatch.setenv("AWS_SHARED_CREDENTIALS_FILE", str(tmp_path / "no-credentials"))
    monkeypatch.setenv("AWS_CONFIG_FILE", str(tmp_path / "no-config"))
    monkeypatch.setenv("AWS_EC2_METADATA_DISABLED", "true")  # no instance-metadata lookups
    monkeypatch.setenv("AWS_MAX_ATTEMPTS", "1")
    s3fs.S3FileSystem.clear_instance_cache()


def test_an_s3_store_without_credentials_or_endpoint(media, kept, tmp_path, capfd, monkeypatch):
    """An S3 store with no credentials in the environment, then with credentials but its
    endpoint down: one line each before any flow starts, nothing written."""
    import socket

    _without_aws_settings(monkeypatch, tmp_path)
    before = snapshot(kept["store"], kept["out"])
    argv = ["reconstruct", media["orbit"], "--out", kept["out"], "--store", "s3://facecap/x"]
    code, _, err = facecap(capfd, *argv)
    assert_one_line_error(code, err, ["no credentials for the store s3://facecap/x",
                                      "set AWS_ACCESS_KEY_ID"])
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]  # nothing listens there once the socket is closed
    monkeypatch.setenv("AWS_ACCESS_KEY_ID", "facecap-test")
    monkeypatch.setenv("AWS_SECRET_ACCESS_KEY", "facecap-test-secret")
    monkeypatch.setenv("AWS_ENDPOINT_URL_S3", f"http://127.0.0.1:{port}")
    import s3fs

    s3fs.S3FileSystem.clear_instance_cache()
    code, _, err = facecap(capfd, *argv)
    assert_one_line_error(code, err, ["the store s3://facecap/x cannot be reached",
                                      "that it is up"])
    s3fs.S3FileSystem.clear_instance_cache()
    assert_kept(before, snapshot(kept["store"], kept["out"]))


def test_files_that_are_not_evaluations_are_not_a_baseline(tmp_path):
    """A junk ``OUT/evaluations/0.json`` (not named by a time) is no evaluation: the newest
    real one is the baseline, as if the junk were not there."""
    from facecap.flows.evaluate import check_history

    history = tmp_path / "evaluations"
    history.mkdir()
    (history / "0.json").write_text("junk")
    assert check_history(tmp_path) == {}
    scores = {"anna/take": {"accuracy": {"median": 0.5}, "completion": {"median": 0.7}}}
    (history / "20260101T000000000000Z.json").write_text(json.dumps({"captures": scores}))
    (history / "notes.json").write_text("[]")
    assert check_history(tmp_path) == scores


def bound_by_file_modes() -> list[str]:
    """The command prefix under which a process obeys file modes: root ignores them unless
    it drops CAP_DAC_OVERRIDE (util-linux's setpriv); nothing for anyone else."""
    if os.geteuid() != 0:
        return []
    if not shutil.which("setpriv"):
        pytest.skip("running as root without setpriv to drop CAP_DAC_OVERRIDE")
    return ["setpriv", "--bounding-set", "-dac_override,-dac_read_search"]


def _run_without_dac_override(argv: list[str]) -> subprocess.CompletedProcess:
    """``facecap ARGV`` in a process that file modes bind."""
    return subprocess.run([*bound_by_file_modes(), sys.executable, "-m", "facecap",
                           *map(str, argv)], capture_output=True, text=True, cwd=ROOT,
                          timeout=600)


@pytest.mark.slow
def test_a_read_only_store(media, kept, tmp_path):
    """A store folder nobody may write: the first lock fails, is not retried (a lasting
    errno) and ends the run with one line; the store is unchanged."""
    os.chmod(kept["store"], 0o555)
    try:
        before = snapshot(kept["store"], kept["out"])
        proc = _run_without_dac_override(["reconstruct", media["orbit"], "--out",
                                          tmp_path / "out", "--store", kept["store"]])
        assert_one_line_error(proc.returncode, proc.stderr,
                              ["cannot lock artifact input-", "permission denied",
                               "check that the location is writable"])
        assert_kept(before, snapshot(kept["store"], kept["out"]))
    finally:
        os.chmod(kept["store"], 0o755)


# --------------------------------------------------------------------------- in a flow


CHEAP_POSES = "keyframes: {keyframe_angle_deg: 10}\nposes: {method: geometric, use_tracks: false}\n"
"""Fewer keyframes and no photometric refinement: the pose stage in ~5 s on 224x128."""

IN_A_FLOW = {
    "static camera": (lambda m, t: ["reconstruct", m["static"]],
                      ["static.mp4: only 1 keyframe", "barely moves", "sweep the phone"]),
    "40 identical frames": (lambda m, t: ["reconstruct", m["still"]],
                            ["still.mp4: only 1 keyframe", "barely moves", "sweep the phone"]),
    "frontal only (the face never turns)": (lambda m, t: ["reconstruct", m["frontal"]],
                                            ["frontal.mp4: only", "barely moves",
                                             "ear to ear"]),
    "no face": (lambda m, t: ["reconstruct", m["orbit"], "--config", _config(t, CHEAP_POSES)],
                ["no face was detected", "the video must show a face"]),
    "photos: one cut short (its header reads)": (
        lambda m, t: ["reconstruct", _photos_with_a_truncated_one(t), "--until", "keyframes"],
        ["photos of anna/img_2.jpg cannot be decoded", "damaged or truncated"]),
}


@pytest.mark.slow
@pytest.mark.parametrize("case", list(IN_A_FLOW))
def test_refused_by_a_stage(case, media, kept, tmp_path, capfd, prefect_server):
    build, expected = IN_A_FLOW[case]
    argv = _with_defaults(build(media, tmp_path), kept)
    before = snapshot(kept["store"], kept["out"])
    code, out, err = facecap(capfd, *argv)
    line = assert_one_line_error(code, err, expected)
    assert "/artifacts/" not in line  # the user's video is named, not the store's copy
    assert_kept(before, snapshot(kept["store"], kept["out"]))


@pytest.mark.slow
def test_full_disk(media, kept, capfd, monkeypatch, prefect_server):
    """The store's disk fills up (ENOSPC on every write): one line, not retried, nothing
    half-written left in the store."""
    from facecap.tasks.store import local

    def disk_full(path, chunks):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))

    monkeypatch.setattr(local, "write_local_file", disk_full)
    before = snapshot(kept["store"], kept["out"])
    code, out, err = facecap(capfd, *_with_defaults(["reconstruct", media["orbit"]], kept))
    assert_one_line_error(code, err, ["no space left on device", "free space"])
    assert_kept(before, snapshot(kept["store"], kept["out"]))
    assert not any((kept["store"] / ".tmp").iterdir())  # no debris of the failed write


def test_dataset_with_odd_names(media, kept, tmp_path, capfd, prefect_server):
    """Spaces, Unicode and '..' inside names are ordinary names: each capture gets its own
    output folder inside OUT and is named in the report; a hidden '..mp4' is skipped. The
    captures here are static, so each fails in its keyframe stage, and the dataset run ends
    with one line naming both."""
    root = tmp_path / "dataset"
    names = [("Zoë Ångström", "take 1"), ("a..b", "x..y")]
    for subject, capture in names:
        (root / subject).mkdir(parents=True)
        shutil.copyfile(media["static"], root / subject / f"{capture}.mp4")
    shutil.copyfile(media["static"], root / "a..b" / "..mp4")
    out = kept["out"] / "dataset out"
    before = snapshot(kept["store"], kept["out"])
    code, _, err = facecap(capfd, "dataset", root, "--out", out, "--store", kept["store"])
    line = assert_one_line_error(code, err, ["2 of 2 captures failed", "barely moves"])
    for subject, capture in names:
        video = (root / subject / f"{capture}.mp4").resolve()
        assert f"{subject}/{capture}: {video}: only 1 keyframe" in line
        assert (out / subject / capture).is_dir()
    summary = json.loads((out / "dataset.json").read_text())
    assert sorted(summary["failed"]) == sorted(f"{s}/{c}" for s, c in names)
    assert_kept(before, snapshot(kept["store"], kept["out"]))


def test_evaluation_does_not_follow_a_link_out_of_the_results(media, kept, tmp_path, capfd,
                                                              prefect_server):
    """A reconstruction in OUT that is a link to a file elsewhere (here a stand-in for a
    secret on the worker) is refused by ``evaluate-dataset``; nothing enters the store."""
    root = tmp_path / "dataset"
    (root / "anna").mkdir(parents=True)
    shutil.copyfile(media["static"], root / "anna" / "take.mp4")
    _scan(root / "anna")
    (root / "anna" / "scan_landmarks.json").write_text(json.dumps([[0.0, 0.0, 0.0]] * 68))
    secret = tmp_path / "elsewhere" / "secret.ply"
    secret.parent.mkdir()
    secret.write_text("not for the store")
    out = kept["out"] / "results"
    (out / "anna" / "take").mkdir(parents=True)
    (out / "anna" / "take" / "mesh.ply").symlink_to(secret)
    before = snapshot(kept["store"], kept["out"])
    code, _, err = facecap(capfd, "evaluate-dataset", root, "--out", out, "--store",
                           kept["store"])
    assert_one_line_error(code, err, ["take/mesh.ply lies outside the results folder"])
    assert_kept(before, snapshot(kept["store"], kept["out"]))


# --------------------------------------------------------------------------- accepted


def _keyframes_of(store: Path, out: Path) -> dict:
    report = json.loads((out / "report.json").read_text())
    key = report["stages"]["keyframes"]["key"]
    return json.loads((open_store(store).get(key) / "keyframes.json").read_text())


@pytest.mark.slow
def test_phone_videos_are_accepted(media, kept, tmp_path, capfd, prefect_server):
    """240 fps, a portrait video stored as landscape + rotation, a variable frame rate and a
    Unicode path: all reach and pass the keyframe stage, with the right sizes and times."""
    from facecap_core.keyframes import select_keyframes

    reference = select_keyframes(media["orbit"])  # the same 40 frames at 30 fps
    unicode_dir = tmp_path / "Zoë Ångström" / "séance 1"
    unicode_dir.mkdir(parents=True)
    shutil.copyfile(media["orbit"], unicode_dir / "prise n°1.mp4")
    results = {}
    for name, video in [("fps240", media["fps240"]), ("portrait", media["portrait"]),
                        ("vfr", media["vfr"]), ("unicode", unicode_dir / "prise n°1.mp4")]:
        out = tmp_path / f"out {name}"
        code, stdout, err = facecap(capfd, "reconstruct", video, "--out", out, "--store",
                                    kept["store"], "--until", "keyframes")
        assert code == 0, err
        results[name] = _keyframes_of(kept["store"], out)
    fast = results["fps240"]
    # The keyframes follow the angle swept, not the frame rate; times are the video's own.
    assert fast["frame_indices"] == reference.indices
    assert np.allclose(fast["times"], np.array(reference.indices) / 240, atol=1e-4)
    assert results["portrait"]["video_size"] == [H, W]  # upright: portrait
    assert len(results["portrait"]["frame_indices"]) >= 5
    vfr = results["vfr"]
    assert np.allclose(vfr["times"], VFR_TIMES[vfr["frame_indices"]], atol=2e-3)
    report = json.loads((tmp_path / "out unicode" / "report.json").read_text())
    assert (report["subject"], report["capture"]) == ("séance 1", "prise n°1")
    assert results["unicode"]["frame_indices"] == reference.indices
    # The page the UI's link opens is the one in the output folder.
    assert (open_store(kept["store"]).read_bytes(report["page"]["key"], "index.html")
            == (tmp_path / "out unicode" / "index.html").read_bytes())
    # Run again: everything comes from the store, and the report says so.
    code, _, err = facecap(capfd, "reconstruct", unicode_dir / "prise n°1.mp4", "--out",
                           tmp_path / "out unicode", "--store", kept["store"], "--until",
                           "keyframes")
    assert code == 0, err
    again = json.loads((tmp_path / "out unicode" / "report.json").read_text())
    assert (again["computed"], again["cached"]) == (0, 1)
    assert again["stages"]["keyframes"] == {**report["stages"]["keyframes"], "cached": True}


# --------------------------------------------------------------------------- security


def test_credentials_come_only_from_the_environment():
    """No store or flow entry point takes a credential; an S3 store is made from its URL
    alone and leaves authentication to botocore's environment."""
    import inspect

    from facecap.flows.capture import reconstruct_capture
    from facecap.flows.dataset import reconstruct_dataset
    from facecap.flows.evaluate import evaluate_dataset
    from facecap.tasks.store import open_store

    secretive = ("key", "secret", "password", "token", "credential", "auth")
    entry_points = [ArtifactStore.__init__, open_store, reconstruct_capture.fn,
                    reconstruct_dataset.fn, evaluate_dataset.fn]
    for function in entry_points:
        names = [p.lower() for p in inspect.signature(function).parameters]
        assert not [n for n in names if any(s in n for s in secretive)], function
    source = (ROOT / "tasks" / "store" / "base.py").read_text()
    assert source.count("url_to_fs(") == 1  # one call: nothing but the URL is passed
    assert "url_to_fs(_expand(url))" in source


def test_served_flows_validate_their_parameters():
    """What a deployment run hands the flow is validated by pydantic before it starts: an
    unknown parameter or a wrong type is refused."""
    from prefect.exceptions import ParameterTypeError, SignatureMismatchError

    from facecap.flows.capture import reconstruct_capture
    from facecap.flows.dataset import reconstruct_dataset
    from facecap.flows.evaluate import evaluate_dataset

    good = reconstruct_capture.validate_parameters({"video": "v.mp4", "out": "o"})
    assert good["video"] == "v.mp4"
    bad = [
        (reconstruct_capture, {"video": "v.mp4", "out": "o", "shell": "rm -rf /"}),
        (reconstruct_capture, {"video": "v.mp4", "out": "o", "until": "everything"}),
        (reconstruct_capture, {"video": ["v.mp4"], "out": "o"}),
        (reconstruct_capture, {"out": "o"}),
        (reconstruct_dataset, {"root": "r", "out": "o", "workers": 64}),
        (reconstruct_dataset, {"root": {"path": "r"}, "out": "o"}),
        (evaluate_dataset, {"root": "r", "out": "o", "tolerance_mm": "lots"}),
    ]
    for flow, parameters in bad:
        with pytest.raises((ParameterTypeError, SignatureMismatchError, TypeError)):
            flow.validate_parameters(parameters)
