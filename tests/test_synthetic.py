"""Synthetic captures: the video decodes, and the ground truth agrees with what was rendered."""

import json

import av
import numpy as np
import pytest

from facecap.synthetic import load_gt_cameras, synthesize
from facecap.synthetic.config import SynthConfig
from facecap_core.camera import camera_center, project
from facecap_core.errors import InputError
from facecap_core.meshio import load_landmarks, load_mesh
from facecap_core.render import RaycastScene


def _frames(video):
    with av.open(str(video)) as c:
        return [f.to_ndarray(format="rgb24") for f in c.decode(video=0)]


@pytest.fixture(scope="module")
def sweep(tmp_path_factory, ict_model):
    """A 1.5 s, 640x360 ear-to-ear sweep of a random ICT identity."""
    config = SynthConfig(subject="ict:3", ict_model=ict_model, width=640, height=360,
                         duration_s=1.5, fps=30, seed=3)
    return config, synthesize(config, tmp_path_factory.mktemp("sweep"), progress=False)


@pytest.mark.slow
def test_video_and_ground_truth_files(sweep):
    config, cap = sweep
    frames = _frames(cap.video)
    assert len(frames) == cap.frames == 45
    assert frames[0].shape == (360, 640, 3)
    intr, poses = load_gt_cameras(cap.gt_cameras)
    assert len(poses) == 45 and 58 < intr.horizontal_fov_deg < 72
    assert config.k1_range[0] <= intr.k1 <= config.k1_range[1] and intr.k2 == -0.25 * intr.k1
    for p in poses:
        np.testing.assert_allclose(p["R"] @ p["R"].T, np.eye(3), atol=1e-9)
    mesh = load_mesh(cap.gt_mesh)
    assert 60 < np.ptp(mesh.vertices[:, 1]) < 400  # a head in mm
    saved = SynthConfig.model_validate(
        __import__("yaml").safe_load((cap.folder / "gt" / "config.yaml").read_text()))
    assert saved == config


@pytest.mark.slow
def test_camera_sweeps_ear_to_ear_at_arm_length(sweep):
    config, cap = sweep
    _, poses = load_gt_cameras(cap.gt_cameras)
    centres = np.array([camera_center(p["R"], p["t"]) for p in poses])
    yaw = np.degrees(np.arctan2(centres[:, 0], centres[:, 2]))
    assert yaw[0] < -80 and yaw[-1] > 80 and np.all(np.diff(yaw) > 0)
    dist = np.linalg.norm(centres - centres.mean(0) * [0, 1, 0], axis=1)
    assert dist.min() > 320 and dist.max() < 540


@pytest.mark.slow
def test_ground_truth_matches_the_rendered_pixels(sweep):
    """Landmarks projected with the GT camera hit the GT mesh at the landmark itself, and the
    rendered head covers exactly the pixels where the GT mesh is closer than the room."""
    _, cap = sweep
    intr, poses = load_gt_cameras(cap.gt_cameras)
    mesh = load_mesh(cap.gt_mesh)
    landmarks = load_landmarks(cap.gt_landmarks)
    assert np.abs(__import__("facecap_core.evaluation", fromlist=["distances"]).distances(
        landmarks, mesh.vertices, mesh.faces)).max() < 0.01  # landmarks lie on the surface
    scene = RaycastScene()
    scene.add(mesh.vertices, mesh.faces)
    frontal = min(range(len(poses)), key=lambda i: abs(camera_center(poses[i]["R"], poses[i]["t"])[0]))
    pose = poses[frontal]
    hits = scene.cast_camera(intr, pose["R"], pose["t"])
    uv, depth = project(landmarks[17:], pose["R"], pose["t"], intr)
    px = np.round(uv).astype(int)
    seen = hits.depth[px[:, 1], px[:, 0]] > depth - 1.0  # not hidden behind the nose
    gap = np.linalg.norm(hits.points[px[seen, 1], px[seen, 0]] - landmarks[17:][seen], axis=1)
    # One pixel is ~0.7 mm on the face here: rounding to the pixel centre moves < 1 mm
    # (a rounded pixel on the lip line may look through the mouth: hence the 90 %).
    assert seen.sum() > 40 and np.median(gap) < 0.5 and np.mean(gap < 1.0) > 0.9


def test_same_seed_same_capture(tmp_path, ict_model):
    config = SynthConfig(subject="ict:5", ict_model=ict_model, width=160, height=90,
                         duration_s=0.2, room=False)
    a = synthesize(config, tmp_path / "a", progress=False)
    b = synthesize(config, tmp_path / "b", progress=False)
    assert json.loads(a.gt_cameras.read_text()) == json.loads(b.gt_cameras.read_text())
    # The rendered frames are identical, but x264 does not always encode identical input to
    # identical bytes: the decoded frames agree to within the encoder's own error (~2 grey
    # levels here), far below the scene's texture.
    diff = np.abs(_frames(a.video)[2].astype(int) - _frames(b.video)[2])
    assert diff.mean() < 4.0


def test_bad_subjects_are_named(tmp_path, monkeypatch):
    monkeypatch.setenv("FACECAP_ICT_MODEL", str(tmp_path / "missing.npz"))
    with pytest.raises(InputError, match="not found"):
        synthesize(SynthConfig(subject="ict:1"), tmp_path, progress=False)
    with pytest.raises(InputError, match="not found"):
        synthesize(SynthConfig(subject="ict:1", ict_model=tmp_path / "none.npz"), tmp_path)
    with pytest.raises(InputError, match="landmarks"):
        synthesize(SynthConfig(subject=str(tmp_path / "head.obj")), tmp_path)
    with pytest.raises(InputError, match="even"):
        synthesize(SynthConfig(subject="james", width=641), tmp_path)


# -- phone-like conditions ------------------------------------------------------------------

from facecap.synthetic import Room, ict_subject, prepare, to_srgb8  # noqa: E402
from facecap_core.camera import rotation_angle_deg  # noqa: E402
from facecap_core.config import build  # noqa: E402
from facecap_core.video import iter_frames, probe  # noqa: E402


def _small(ict_model, **kw) -> SynthConfig:
    """A tiny noiseless capture: exact comparisons between renders."""
    values = dict(subject="ict:4", ict_model=ict_model, width=128, height=72, duration_s=0.4,
                  fps=30, seed=4, read_noise=0.0, shot_noise=0.0)
    return SynthConfig(**{**values, **kw})


@pytest.mark.parametrize("rotation", [0, 90])
def test_rolling_shutter_line_is_the_global_shutter_render_at_its_time(ict_model, rotation):
    """Each sensor line of a rolling-shutter frame (a row; a column of the upright image in
    portrait) is exactly the global-shutter render at that line's time."""
    rs = prepare(_small(ict_model, rolling_shutter_s=0.03, blur_samples=1,
                        display_rotation_deg=rotation))
    gs = prepare(_small(ict_model, blur_samples=1, display_rotation_deg=rotation))
    time = rs.frame_time(6)
    image, _, _ = rs.render(time)
    offsets = rs.readout.offsets
    assert len(offsets) == 72 and np.isclose(offsets[-1] - offsets[0], 0.03 * 71 / 72)
    assert np.isclose(offsets.mean(), 0.0)  # the GT instant is mid-readout
    for line in (0, 35, 71):
        mask = rs.readout.lines == line
        assert mask.sum() == 128  # a whole sensor row, wherever it lies upright
        at_line, _, _ = gs.render(time + offsets[line])
        diff = np.abs(image[mask] - at_line[mask])
        assert np.median(diff) < 1e-9 and np.mean(diff > 1e-6) < 0.02
    # and the shutter matters: the first line differs from the mid-readout global render
    mid, _, _ = gs.render(time)
    first = rs.readout.lines == 0
    assert np.abs(image[first] - mid[first]).mean() > 1e-3


@pytest.mark.parametrize("rotation", [90, 270])
def test_portrait_decodes_upright(tmp_path, ict_model, rotation):
    config = _small(ict_model, display_rotation_deg=rotation, duration_s=0.1)
    cap = synthesize(config, tmp_path, progress=False)
    info = probe(cap.video)
    assert (info.width, info.height, info.rotation_deg) == (72, 128, rotation)
    with av.open(str(cap.video)) as c:
        stored = next(c.decode(video=0))
        assert (stored.width, stored.height) == (128, 72)  # landscape in the file
    upright = next(iter_frames(cap.video)).image
    expected = to_srgb8(prepare(config).frame(0).image)
    assert upright.shape == expected.shape == (128, 72, 3)
    err = np.abs(upright.astype(int) - expected).mean()
    assert err < 3.0 and np.abs(upright.astype(int) - expected[::-1, ::-1]).mean() > 5 * err
    doc = json.loads(cap.gt_cameras.read_text())
    assert (doc["width"], doc["height"], doc["display_rotation_deg"]) == (72, 128, rotation)
    intr, _ = load_gt_cameras(cap.gt_cameras)
    assert (intr.width, intr.height) == (72, 128)


def test_sway_moves_the_head_by_the_configured_amount(ict_model):
    shot = prepare(_small(ict_model, sway_mm=3.0, duration_s=2.0))
    heads = [shot.sway.pose(shot.frame_time(i)) for i in range(shot.frames)]
    shift = np.array([np.linalg.norm(c) for R, c in heads])
    assert np.allclose([R for R, _ in heads], np.eye(3))
    assert np.isclose(shift.max(), 3.0) and shift.min() < 2.5  # it moves, by at most 3 mm
    turn = prepare(_small(ict_model, sway_deg=1.0, duration_s=2.0))
    angles = [rotation_angle_deg(turn.sway.pose(turn.frame_time(i))[0], np.eye(3))
              for i in range(turn.frames)]
    assert np.isclose(max(angles), 1.0, atol=1e-6)


def test_swaying_head_ground_truth_cameras_are_head_relative(ict_model):
    """The head's rendered points, taken back into the head frame, project through the GT
    camera onto their own pixels: the GT mesh and cameras stay exact while the head moves."""
    shot = prepare(_small(ict_model, sway_mm=4.0, sway_deg=1.0, blur_samples=1))
    f = shot.frame(9)
    head = f.hits.mesh == 0
    R_h, c_h = f.head
    p_head = (f.hits.points[head] - c_h) @ R_h
    uv, _ = project(p_head, f.R, f.t, shot.intrinsics)
    v, u = np.nonzero(head)
    assert np.abs(uv - np.stack([u, v], 1)).max() < 1e-3
    room_R, room_t = shot.path.pose(f.time)  # the room camera differs by the sway
    assert np.linalg.norm(camera_center(f.R, f.t) - camera_center(room_R, room_t)) > 0.5


def test_plain_walls_have_uniform_albedo():
    plain = Room.random(np.random.default_rng(7), plain=True)
    textured = Room.random(np.random.default_rng(7))
    np.testing.assert_array_equal(plain.vertices, textured.vertices)  # the same room
    rng = np.random.default_rng(0)
    tri = rng.integers(len(plain.faces), size=4000)
    bary = rng.dirichlet([1, 1, 1], size=4000)
    points = np.einsum("nc,nck->nk", bary, plain.vertices[plain.faces[tri]])
    alb = plain.albedo(tri, bary, points)
    colours = {}
    for k, c in zip(plain.face_texture[tri], alb):
        colours.setdefault(k, []).append(c)
    assert all(np.ptp(np.array(c), axis=0).max() < 1e-6 for c in colours.values())
    rich = textured.albedo(tri, bary, points)
    assert np.std(rich[plain.face_texture[tri] == plain.face_texture[tri][0]], axis=0).max() > 0.02


def test_smooth_skin_attenuates_the_fine_texture(ict_model):
    def detail(subject):
        # Albedo along a 40 mm line over the cheek, every 0.1 mm; its fine texture is the
        # residual after a 2 mm moving average.
        lm = subject.landmarks
        start = lm[1] + 0.4 * (lm[30] - lm[1])
        points = start + np.linspace(0, 40, 401)[:, None] * np.array([0, 1, 0])
        tri = np.zeros(len(points), int)  # skin faces come first
        lum = subject.albedo(tri, np.full((len(points), 3), 1 / 3), points).mean(1)
        smooth = np.convolve(lum, np.ones(21) / 21, mode="same")
        return np.std((lum - smooth)[20:-20]) / lum.mean()

    full = detail(ict_subject(ict_model, 2))
    assert detail(ict_subject(ict_model, 2, skin_detail=1.0)) == full
    assert detail(ict_subject(ict_model, 2, skin_detail=0.3)) < 0.45 * full
    assert detail(ict_subject(ict_model, 2, skin_detail=0.0)) < 0.2 * full


def test_hevc_and_conditions_in_the_ground_truth(tmp_path, ict_model):
    config = _small(ict_model, codec="hevc", rolling_shutter_s=0.03, sway_mm=2.0,
                    duration_s=0.1)
    cap = synthesize(config, tmp_path, progress=False)
    with av.open(str(cap.video)) as c:
        stream = c.streams.video[0]
        assert stream.codec_context.name == "hevc" and stream.codec_tag == "hvc1"
        assert len(list(c.decode(video=0))) == cap.frames == 3
    doc = json.loads(cap.gt_cameras.read_text())
    assert doc["rolling_shutter"]["readout_s"] == 0.03 and doc["sway"]["sway_mm"] == 2.0
    first = doc["frames"][0]
    assert first["time"] == pytest.approx(config.exposure_fraction / 60 + 0.015, abs=1e-6)
    assert np.asarray(first["head_R"]).shape == (3, 3)
    # a default capture's ground truth carries none of it
    plain = synthesize(_small(ict_model, duration_s=0.1), tmp_path / "plain", progress=False)
    assert not {"rolling_shutter", "sway", "display_rotation_deg"} & set(
        json.loads(plain.gt_cameras.read_text()))


def test_condition_settings_are_checked(tmp_path):
    with pytest.raises(InputError, match="frame interval"):
        build(SynthConfig, {"fps": 120, "rolling_shutter_s": 0.03})
    with pytest.raises(InputError, match="display_rotation_deg"):
        build(SynthConfig, {"display_rotation_deg": 45})
    with pytest.raises(InputError, match="skin_detail"):
        synthesize(SynthConfig(subject="james", skin_detail=0.5), tmp_path, progress=False)


def test_sensor_image_models_a_phone_sensor():
    """The phone effects on a known image: defaults are Poisson–Gaussian noise and sRGB
    only; a colour filter array over a flat colour demosaics back to it; the lens blur is a
    Gaussian of the given width; sharpening amplifies the noise."""
    from facecap.synthetic.sensor import sensor_image, to_srgb8

    flat = np.full((64, 64, 3), [0.2, 0.45, 0.1], np.float32)  # renders are float32
    quiet = SynthConfig(read_noise=0.0, shot_noise=0.0)
    base = SynthConfig()
    rng_a, rng_b = np.random.default_rng(7), np.random.default_rng(7)
    sigma = np.sqrt(base.read_noise ** 2 + base.shot_noise ** 2 * flat)
    expected = to_srgb8(flat + sigma * rng_b.standard_normal(flat.shape))
    assert np.array_equal(sensor_image(flat, base, rng_a), expected)

    mosaic = sensor_image(flat, quiet.model_copy(update={"bayer": True}),
                          np.random.default_rng(0))
    assert np.abs(mosaic.astype(int) - to_srgb8(flat).astype(int)).max() <= 1

    # A vertical step edge blurred by a Gaussian of σ = 2 px: 10-90 % rise over 2.563 σ.
    step = np.zeros((32, 128, 3))
    step[:, 64:] = 1.0
    soft = SynthConfig(read_noise=0.0, shot_noise=0.0, defocus_px=2.0)
    linear = sensor_image(step, soft, np.random.default_rng(0))[16, :, 0].astype(float)
    srgb = to_srgb8(np.array([0.1, 0.9]))  # the 10 % and 90 % levels, encoded
    rise = np.interp(srgb[1], linear, np.arange(128)) - np.interp(srgb[0], linear,
                                                                    np.arange(128))
    assert rise == pytest.approx(2.563 * 2.0, abs=0.3)

    noisy = SynthConfig(read_noise=0.02, shot_noise=0.0)
    plain = sensor_image(flat, noisy, np.random.default_rng(1)).astype(float)
    sharp = sensor_image(flat, noisy.model_copy(update={"sharpen": 1.0}),
                         np.random.default_rng(1)).astype(float)
    assert np.all(sharp.std(axis=(0, 1)) > 1.3 * plain.std(axis=(0, 1)))  # per channel


# -- the output folder ------------------------------------------------------------------


def test_synth_writes_no_result_through_a_link_nor_over_its_input(tmp_path, ict_model,
                                                                 monkeypatch, capfd):
    """Links planted in ``--out`` at the results' names are replaced, not written through;
    a capture's own ground truth given back as its subject, and a store artifact's folder as
    ``--out``, are refused before anything is rendered, with one line."""
    from facecap.cli import main
    from facecap.tasks.store import artifact_key, open_store
    from tests.test_bad_inputs import assert_one_line_error

    monkeypatch.setenv("FACECAP_HOME", str(tmp_path / "home"))
    out, secret = tmp_path / "out", tmp_path / "secret.txt"
    secret.write_text("the user's own file")
    (out / "gt").mkdir(parents=True)
    for name in ("video.mp4", "gt/mesh.ply", "gt/cameras.json", "gt/landmarks.json"):
        (out / name).symlink_to(secret)
    cap = synthesize(_small(ict_model, duration_s=0.1), out, progress=False)
    assert secret.read_text() == "the user's own file"
    for path in (cap.video, cap.gt_mesh, cap.gt_cameras, cap.gt_landmarks):
        assert path.is_file() and not path.is_symlink(), path
    assert load_mesh(cap.gt_mesh).vertices.shape[1] == 3

    mesh = cap.gt_mesh.read_bytes()
    code = main(["synth", "--out", str(out), "--subject", str(cap.gt_mesh),
                 "--subject-landmarks", str(cap.gt_landmarks), "--width", "128", "--height",
                 "72", "--seconds", "0.1", "--quiet"])
    assert_one_line_error(code, capfd.readouterr().err,
                          [f"would replace the input {cap.gt_mesh}", "another --out"])
    assert cap.gt_mesh.read_bytes() == mesh

    store = open_store(tmp_path / "home" / "store")
    key = artifact_key("ingest", {}, {"name": "video.mp4"}, "1")
    store.put(key, {"video.mp4": b"a stored capture"}, stage="ingest", inputs={},
              config={"name": "video.mp4"}, version="1")
    folder = tmp_path / "home" / "store" / "artifacts" / key
    assert (folder / "video.mp4").read_bytes() == b"a stored capture"
    code = main(["synth", "--out", str(folder), "--ict-model", str(ict_model), "--width",
                 "128", "--height", "72", "--seconds", "0.1", "--quiet"])
    assert_one_line_error(code, capfd.readouterr().err, ["keeps for itself", "another --out"])
    assert (folder / "video.mp4").read_bytes() == b"a stored capture"
    store.verify(key)  # the store still vouches for it
