"""Known-answer tests of the evaluation protocol (facecap_core.evaluation).

The ground truth is a smooth synthetic "head": an ellipsoid (75, 100, 90) mm with a nose,
brows and chin raised on its front (+z), so that alignment has a unique answer, and 68
landmarks placed on it by casting rays along -z from a frontal layout (iBUG order: 30 nose
tip, 36/45 outer eye corners at x = -45/+45, 27 nasion and 33 nose base on the midline).
The ear region is tested on ICT Face Model heads, which have ears.
"""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import open3d as o3d
import pytest
import trimesh
from pydantic import ValidationError

from facecap.ear_training.contour import SIDES, load_contour_file
from facecap_core.camera import rotation_matrix
from facecap_core.errors import InputError
from facecap_core.evaluation import (
    COLORBAR_HEIGHT,
    EAR_CENTRE_OFFSET,
    EAR_RADIUS_FACTOR,
    EvaluationConfig,
    align,
    distances,
    ear_region,
    ear_spheres,
    error_heatmap,
    evaluate,
    face_region,
    face_size,
    paper_table,
    region_sphere,
    score,
    score_json,
)
from facecap_core.landmarks.ears import CONTOUR_FILE, MODELS_DIR
from facecap_core.meshio import load_landmarks, save_landmarks
from facecap_core.render import vertex_normals
from facecap_core.template import Template


def _landmark_layout() -> np.ndarray:
    """Frontal (x, y) positions in mm of the 68 iBUG landmarks; +x is the subject's left."""
    xy = np.zeros((68, 2))
    a = np.linspace(-np.pi / 2, np.pi / 2, 17)
    xy[0:17] = np.stack([65 * np.sin(a), -40 - 40 * np.cos(a)], 1)  # jaw, right to left
    xy[17:22] = np.stack([np.linspace(-50, -15, 5), np.full(5, 48.0)], 1)
    xy[22:27] = np.stack([np.linspace(15, 50, 5), np.full(5, 48.0)], 1)
    xy[27:31] = np.stack([np.zeros(4), np.linspace(35, 2, 4)], 1)  # 27 nasion .. 30 tip
    xy[31:36] = np.stack([np.linspace(-14, 14, 5), np.full(5, -13.0)], 1)  # 33 nose base
    b = np.linspace(np.pi, -np.pi, 7)[:6]
    for start, cx in ((36, -33.0), (42, 33.0)):  # 36 / 45: outer corners at x = -45 / +45
        xy[start:start + 6] = np.stack([cx + 12 * np.cos(b), 35 + 4 * np.sin(b)], 1)
    c = np.linspace(0, 2 * np.pi, 13)[:12]
    xy[48:60] = np.stack([-25 * np.cos(c), -40 + 8 * np.sin(c)], 1)
    d = np.linspace(0, 2 * np.pi, 9)[:8]
    xy[60:68] = np.stack([-18 * np.cos(d), -40 + 3 * np.sin(d)], 1)
    return xy


def make_head() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Synthetic head scan: vertices (10242, 3) mm, faces, and 68 landmarks on its surface."""
    sphere = trimesh.creation.icosphere(subdivisions=5)
    u = np.asarray(sphere.vertices)
    v = u * np.array([75.0, 100.0, 90.0])
    x, y = v[:, 0], v[:, 1]
    bumps = (22.0 * np.exp(-(x / 11.0) ** 2 - ((y - 5.0) / 22.0) ** 2)  # nose
             + 8.0 * np.exp(-(x / 25.0) ** 2 - ((y + 70.0) / 15.0) ** 2)  # chin
             + 6.0 * np.exp(-(np.abs(x) - 30.0) ** 2 / 15.0 ** 2 - ((y - 45.0) / 8.0) ** 2))
    v = v + (bumps * np.clip(u[:, 2], 0, None) ** 2)[:, None] * u  # front half only
    f = np.asarray(sphere.faces)

    xy = _landmark_layout()
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(v.astype(np.float32)), o3d.core.Tensor(f.astype(np.uint32)))
    rays = np.concatenate([np.c_[xy, np.full(68, 500.0)], np.tile([0.0, 0.0, -1.0], (68, 1))], 1)
    t_hit = scene.cast_rays(o3d.core.Tensor(rays.astype(np.float32)))["t_hit"].numpy()
    assert np.all(np.isfinite(t_hit))
    return v, f, np.c_[xy, 500.0 - t_hit]


@pytest.fixture(scope="module")
def head():
    return make_head()


def similarity(seed: int, max_deg: float = 30.0, max_t: float = 20.0, scales=(0.9, 1.1)):
    """A seeded random similarity transform x -> s R x + t, returned with its parts."""
    rng = np.random.default_rng(seed)
    R = rotation_matrix(rng.normal(size=3), math.radians(rng.uniform(0.3, 1.0) * max_deg))
    t = rng.uniform(-max_t, max_t, 3)
    s = rng.uniform(*scales)
    return (lambda x: s * np.asarray(x) @ R.T + t), s, R, t


def crop(v, f, keep):
    """The sub-mesh of the kept vertices (triangles with all corners kept)."""
    new_index = np.cumsum(keep) - 1
    return v[keep], new_index[f[keep[f].all(axis=1)]]


# --------------------------------------------------------------------------- building blocks


def test_distances_are_point_to_triangle_not_point_to_vertex():
    v = np.array([[0.0, 0, 0], [10, 0, 0], [0, 10, 0]])
    f = np.array([[0, 1, 2]])
    pts = np.array([[2.0, 2, 3],  # above the interior: the height
                    [-3, -4, 0],  # beyond corner 0: distance to the corner
                    [5, -2, 1],  # beyond edge 0-1: distance to the edge
                    [6, 6, 0]])  # beyond the hypotenuse, in plane
    expected = [3.0, 5.0, math.sqrt(5.0), math.sqrt(2.0)]
    np.testing.assert_allclose(distances(pts, v, f), expected, atol=1e-5)


def test_region_sphere_is_nose_tip_and_scaled_face_size():
    lm = np.zeros((68, 3))
    lm[30] = [1.0, 2.0, 3.0]
    lm[36], lm[45] = [-45.0, 30, 0], [45.0, 30, 0]  # 90 mm
    lm[27], lm[33] = [0.0, 35, 0], [0.0, -15, 0]  # 50 mm
    centre, radius = region_sphere(lm, 1.4)
    np.testing.assert_array_equal(centre, [1.0, 2.0, 3.0])
    assert radius == pytest.approx(1.4 * 70.0)
    pts = np.array([[1.0, 2.0, 3.0 + 97.9], [1.0, 2.0, 3.0 + 98.1]])
    assert face_region(pts, lm).tolist() == [True, False]
    with pytest.raises(InputError):
        region_sphere(lm[:, :2], 1.4)


def test_synthetic_head_has_adult_face_proportions(head):
    v, f, lm = head
    centre, radius = region_sphere(lm, 1.4)
    assert np.linalg.norm(lm[36] - lm[45]) == pytest.approx(90.0, abs=1e-6)
    assert 90.0 < radius < 105.0  # about 95 mm, as on an adult face
    assert lm[30, 2] == pytest.approx(v[:, 2].max(), abs=1.0)  # landmark 30 on the nose tip
    assert 1500 < face_region(v, lm).sum() < 4000


# --------------------------------------------------------------------------- known answers


@pytest.mark.parametrize("protocol", ["similarity", "metric"])
@pytest.mark.parametrize("with_landmarks", [True, False])
def test_scan_against_itself_scores_zero(head, protocol, with_landmarks):
    v, f, lm = head
    sc = score(v, f, v, f, lm, lm if with_landmarks else None, protocol=protocol)
    for side in (sc.accuracy, sc.completion):
        assert side.mean < 1e-3 and side.under_1mm == 1.0 and side.count > 1500
    assert sc.scale == pytest.approx(1.0, abs=1e-6)
    np.testing.assert_allclose(sc.matrix, np.eye(4), atol=1e-6)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_similarity_transform_is_recovered(head, seed):
    v, f, lm = head
    T, s, R, t = similarity(seed)
    sc = score(T(v), f, v, f, lm, T(lm), protocol="similarity")
    assert abs(sc.scale * s - 1.0) < 1e-3  # the inverse scale is recovered
    assert sc.accuracy.mean < 0.01 and sc.completion.mean < 0.01
    np.testing.assert_allclose(sc.alignment.apply(T(v)), v, atol=1e-3)


@pytest.mark.parametrize("seed", [0, 2])
def test_icp_refines_noisy_landmark_alignment(head, seed):
    # Landmarks off by 1.5 mm (a detector's error) only start the fit; ICP must finish it.
    v, f, lm = head
    T, s, _, _ = similarity(seed)
    noisy_lm = lm + np.random.default_rng(seed).normal(scale=1.5, size=lm.shape)
    sc = score(T(v), f, v, f, lm, T(noisy_lm), protocol="similarity")
    assert abs(sc.scale * s - 1.0) < 1e-3
    assert sc.accuracy.mean < 0.02
    assert sc.alignment.iterations > 1


def test_icp_without_landmarks_recovers_small_misalignment(head):
    v, f, lm = head
    T, s, _, _ = similarity(4, max_deg=5.0, max_t=4.0, scales=(0.97, 1.03))
    config = EvaluationConfig(max_iterations=300)
    sc = score(T(v), f, v, f, lm, None, protocol="similarity", config=config)
    assert abs(sc.scale * s - 1.0) < 1e-3
    assert sc.accuracy.mean < 0.01
    al = align(T(v), f, v, f, lm, None, with_scale=True, config=config)
    np.testing.assert_allclose(al.matrix, sc.matrix, atol=1e-9)
    assert al.rms < 0.01


def test_normal_noise_gives_half_normal_errors(head):
    # |N(0, 1)| has mean sqrt(2/pi) = 0.798 and median 0.674.
    v, f, lm = head
    rng = np.random.default_rng(7)
    noisy = v + rng.normal(size=len(v))[:, None] * vertex_normals(v, f)
    sc = score(noisy, f, v, f, lm, lm, protocol="similarity")
    assert 0.7 < sc.accuracy.mean < 0.9
    assert 0.6 < sc.accuracy.median < 0.75
    assert abs(sc.scale - 1.0) < 0.01


def test_cropped_mesh_is_accurate_but_incomplete(head):
    v, f, lm = head
    cv, cf = crop(v, f, np.linalg.norm(v - lm[30], axis=1) < 50.0)
    for protocol in ("similarity", "metric"):
        sc = score(cv, cf, v, f, lm, lm, protocol=protocol)
        assert sc.accuracy.mean < 0.05
        assert sc.completion.mean > 5.0 and sc.completion.under_2mm < 0.7
        # per-vertex arrays: every mesh vertex / scan vertex, nan outside the face sphere
        assert sc.accuracy_per_vertex.shape == (len(cv),)
        assert sc.completion_per_vertex.shape == (len(v),)
        assert np.isnan(sc.completion_per_vertex).sum() == len(v) - sc.completion.count


def test_wrongly_scaled_mesh_passes_similarity_and_fails_metric(head):
    v, f, lm = head
    big_v, big_lm = 1.05 * v, 1.05 * lm
    sim = score(big_v, f, v, f, lm, big_lm, protocol="similarity")
    assert sim.scale == pytest.approx(1 / 1.05, rel=1e-3)
    assert sim.accuracy.mean < 0.01 and sim.completion.mean < 0.01
    met = score(big_v, f, v, f, lm, big_lm, protocol="metric")
    assert met.scale == 1.0
    # On this smooth head the best rigid fit of a 5 % larger face leaves ~0.6 mm on average.
    assert met.accuracy.mean > 0.4 and met.completion.mean > 0.4
    assert met.accuracy.under_1mm < 0.95


# --------------------------------------------------------------------------- files


@pytest.fixture()
def head_files(head, tmp_path):
    v, f, lm = head
    scan = tmp_path / "scan.ply"
    trimesh.Trimesh(v, f, process=False).export(scan)
    scan_lm = save_landmarks(tmp_path / "scan_landmarks.json", lm)
    T, _, _, _ = similarity(5)
    mesh = tmp_path / "mesh.obj"
    trimesh.Trimesh(T(v), f, process=False).export(mesh)
    mesh_lm = save_landmarks(tmp_path / "mesh_landmarks.json", T(lm))
    return mesh, scan, scan_lm, mesh_lm


def test_evaluate_files(head_files):
    mesh, scan, scan_lm, mesh_lm = head_files
    result = evaluate(mesh, scan, scan_lm, mesh_lm)
    assert set(result) == {"similarity", "metric"}
    assert result["similarity"].accuracy.mean < 0.01
    assert result["metric"].scale == 1.0
    json.dumps(result["metric"].to_dict())  # JSON-ready
    # The mesh's landmarks as the points themselves: the same scores as from their file.
    given = evaluate(mesh, scan, scan_lm, load_landmarks(mesh_lm))
    assert given["metric"].accuracy.mean == pytest.approx(result["metric"].accuracy.mean)
    with pytest.raises(InputError, match="shape"):
        evaluate(mesh, scan, scan_lm, np.zeros((5, 3)))


def test_missing_scan_landmarks_is_a_one_line_input_error(head_files):
    mesh, scan, _, mesh_lm = head_files
    with pytest.raises(InputError, match="landmarks") as exc:
        evaluate(mesh, scan, None, mesh_lm)
    assert str(scan) in str(exc.value) and "\n" not in str(exc.value)


def test_bad_files_are_input_errors(head_files, tmp_path):
    mesh, scan, scan_lm, _ = head_files
    with pytest.raises(InputError, match="not found"):
        evaluate(tmp_path / "missing.ply", scan, scan_lm)
    text = tmp_path / "mesh.txt"
    text.write_text("not a mesh\n")
    with pytest.raises(InputError):
        evaluate(text, scan, scan_lm)
    garbage = tmp_path / "garbage.ply"
    garbage.write_bytes(bytes(range(256)) * 8)
    with pytest.raises(InputError):
        evaluate(mesh, garbage, scan_lm)
    with pytest.raises(InputError, match="protocol"):
        evaluate(mesh, scan, scan_lm, protocols=("affine",))


# --------------------------------------------------------------------------- reports


def test_score_json_has_the_reported_keys(head):
    v, f, lm = head
    doc = score_json(score(v, f, v, f, lm, lm, protocol="metric"))
    assert set(doc) - {"protocol"} == {"accuracy", "completion", "scale", "ears"}
    assert set(doc["ears"]) == {"accuracy", "completion"}
    for side in (doc["accuracy"], doc["completion"], doc["ears"]["accuracy"],
                 doc["ears"]["completion"]):
        assert set(side) == {"mean", "std", "median", "under_1mm", "under_2mm"}
        assert all(isinstance(x, float) for x in side.values())
    assert doc["scale"] == 1.0
    json.dumps(doc)


def test_error_heatmap_png(head, tmp_path):
    v, f, lm = head
    errors = np.where(face_region(v, lm), np.abs(v[:, 0]) / 15.0, np.nan)  # 0..5 mm, nan outside
    out = error_heatmap(v, f, errors, tmp_path / "figs" / "heat.png", max_mm=5.0)
    img = cv2.imread(str(out))
    assert img.shape == (480 + COLORBAR_HEIGHT, 3 * 480, 3)
    views = img[:480].astype(int)
    spread = views.max(axis=2) - views.min(axis=2)
    coloured = spread > 40
    grey = (spread == 0) & (views[..., 0] > 30) & (views[..., 0] < 230)
    assert coloured.sum() > 20000 and grey.sum() > 5000
    # The front view sees the coloured face; the profiles see coloured and grey parts.
    assert coloured[:, :480].sum() > coloured[:, 480:].sum() / 2
    bar = img[480:].astype(int)
    assert (bar.max(axis=2) - bar.min(axis=2) > 40).sum() > 1000  # the colour ramp


def test_preview_is_the_heat_map_with_a_scan_and_the_coloured_mesh_without(head, tmp_path):
    """``preview.png``: never a colour bar over a plain mesh. Without a scan, the mesh in its
    own vertex colours (red on the subject's left, blue on the right); with one, the metric
    heat map."""
    import trimesh

    from facecap.flows.ui import mesh_preview

    v, f, lm = head
    colours = np.where(v[:, :1] > 0, [[220, 30, 30]], [[30, 30, 220]]).astype(np.uint8)
    trimesh.Trimesh(v, f, vertex_colors=colours, process=False).export(tmp_path / "mesh.ply")
    img = cv2.imread(str(mesh_preview({"mesh.ply": tmp_path / "mesh.ply"},
                                      tmp_path / "preview.png")))  # BGR
    assert img.shape == (320, 3 * 320, 3)  # three views, no colour bar
    front = img[:, :320].astype(int)
    red = (front[..., 2] > front[..., 0] + 60).sum()
    blue = (front[..., 0] > front[..., 2] + 60).sum()
    assert red > 3000 and blue > 3000, (red, blue)
    # The subject's left is on the viewer's right in the front view.
    cols = np.arange(320)[None, :]
    assert ((front[..., 2] > front[..., 0] + 60) * cols).sum() / red > 160
    heat = error_heatmap(v, f, np.abs(v[:, 0]) / 15.0, tmp_path / "heatmap_metric.png")
    results = {"mesh.ply": tmp_path / "mesh.ply", "heatmap_metric.png": heat}
    assert mesh_preview(results, tmp_path / "p.png").read_bytes() == heat.read_bytes()
    assert mesh_preview({}, tmp_path / "none.png") is None  # no mesh, no preview


def test_paper_table_conventions():
    def rec(acc_mean, acc_median, comp_mean, comp_median):
        def side(m, md):
            return {"mean": m, "std": 0.5, "median": md, "under_1mm": 0.5, "under_2mm": 0.8}

        return {"accuracy": side(acc_mean, acc_median),
                "completion": side(comp_mean, comp_median), "scale": 1.0}

    table = paper_table([("Ours", [rec(1.0, 0.8, 2.0, 1.5), rec(2.0, 1.6, 4.0, 2.5)]),
                         ("Single", [rec(1.234, 1.111, 3.0, 2.0)])])
    lines = table.splitlines()
    assert lines[0] == ("| Method | Captures | Accuracy mean | std | median "
                        "| Completion mean | std | median |")
    # mean of means 1.5, std of means 0.5, mean of medians 1.2; completion 3.0, 1.0, 2.0
    assert "| Ours | 2 | 1.50 | 0.50 | 1.20 | 3.00 | 1.00 | 2.00 |" in lines
    assert "| Single | 1 | 1.23 | 0.00 | 1.11 | 3.00 | 0.00 | 2.00 |" in lines
    assert "median: mean over captures of the per-capture median" in table


def test_paper_table_of_the_ear_region_leaves_out_captures_without_figures():
    def side(m, md):
        return {"mean": m, "std": 0.5, "median": md, "under_1mm": 0.5, "under_2mm": 0.8}

    def rec(ears_acc, ears_comp):
        return {"accuracy": side(9.0, 9.0), "completion": side(9.0, 9.0), "scale": 1.0,
                "ears": {"accuracy": side(*ears_acc), "completion": side(*ears_comp)}}

    nan = float("nan")
    without_ears = {"accuracy": side(9.0, 9.0), "completion": side(9.0, 9.0), "scale": 1.0}
    table = paper_table([("Ours", [rec((1.0, 0.8), (2.0, 1.5)), rec((nan, nan), (4.0, 2.5)),
                                   without_ears]),
                         ("Cropped", [rec((nan, nan), (6.0, 5.0))])], region="ears")
    lines = table.splitlines()
    # accuracy: the one capture with ear vertices; completion: the two with figures
    assert "| Ours | 3 | 1.00 | 0.00 | 0.80 | 3.00 | 1.00 | 2.00 |" in lines
    assert "| Cropped | 1 | – | – | – | 6.00 | 0.00 | 5.00 |" in lines
    assert "Ear region" in table and "per-capture median" in table
    assert "| Ours | 3 | 9.00 |" in paper_table([("Ours", [rec((1, 1), (1, 1))] * 3)])
    with pytest.raises(InputError, match="region"):
        paper_table([], region="neck")


# --------------------------------------------------------------------------- ear region


def ict_head(model, seed: int | None) -> Template:
    """The skin of ``ict:SEED`` (the coefficients ict_subject draws; None: the mean face)."""
    coefficients = None if seed is None else np.random.default_rng([seed, 1]).standard_normal(100)
    return Template.from_ict(model, coefficients)


@pytest.fixture(scope="module")
def ict_mean(ict_model) -> Template:
    return ict_head(ict_model, None)


def test_ear_spheres_sit_at_the_offset_in_the_landmark_frame_and_scale_with_the_head():
    lm = np.zeros((68, 3))
    lm[36:42], lm[42:48] = [-45.0, 30, 0], [45.0, 30, 0]  # eye centres: x is the subject's left
    lm[27], lm[33], lm[8] = [0.0, 35, 0], [0.0, -15, 0], [0.0, -80, 0]  # y up
    lm[16], lm[0] = [70.0, 0, -10], [-70.0, 0, -10]
    size = face_size(lm)
    assert size == pytest.approx(70.0)
    centres, radius = ear_spheres(lm)
    out, up, forwards = EAR_CENTRE_OFFSET * size
    np.testing.assert_allclose(centres, [[70.0 + out, up, -10 + forwards],
                                         [-70.0 - out, up, -10 + forwards]], atol=1e-12)
    assert radius == pytest.approx(EAR_RADIUS_FACTOR * size)
    assert 50.0 < radius < 60.0  # about 55 mm on an adult face
    # A rotated, moved and 1.3 times larger head carries its spheres along.
    T, _, _, _ = similarity(3, max_deg=60.0, scales=(1.3, 1.3))
    moved_centres, moved_radius = ear_spheres(T(lm))
    np.testing.assert_allclose(moved_centres, T(centres), atol=1e-9)
    assert moved_radius == pytest.approx(1.3 * radius)
    outwards = np.array([[1.0, 0, 0], [-1.0, 0, 0]])
    pts = np.concatenate([centres + 0.99 * radius * outwards, centres + 1.01 * radius * outwards])
    assert ear_region(pts, lm).tolist() == [True, True, False, False]
    assert ear_region(T(pts), T(lm)).tolist() == [True, True, False, False]


@pytest.mark.parametrize("seed", [None, 1200, 1201, 1202])  # not calibration, not benchmark heads
def test_ear_region_holds_the_ears_of_ict_heads_and_misses_the_face(ict_model, seed):
    head = ict_head(ict_model, seed)
    v, lm = head.vertices, head.landmark_points
    contour = load_contour_file(MODELS_DIR / CONTOUR_FILE)["ict"]
    centres, radius = ear_spheres(lm)
    lateral = np.sign(v[:, 0] - (lm[0, 0] + lm[16, 0]) / 2)  # the ICT head looks along +z
    for side, centre, outwards in zip(SIDES, centres, (1, -1)):
        ear = np.concatenate([contour[side].on(v),  # the outer rim, helix to lobe
                              v[head.regions["ears"] & (lateral == outwards)]])
        assert len(ear) > 300
        # Each ear lies in its own sphere with room to spare, and outside the face sphere.
        assert np.linalg.norm(ear - centre, axis=1).max() < radius - 5.0
        assert ear_region(ear, lm).all() and not face_region(ear, lm).any()
    in_ears, in_face = ear_region(v, lm), face_region(v, lm)
    assert not (in_ears & in_face).any()  # disjoint regions
    assert 1500 < in_ears.sum() < 3500 and in_face.sum() > 4000


@pytest.mark.parametrize("protocol", ["similarity", "metric"])
def test_error_on_the_ears_shows_in_the_ear_region_only(ict_mean, protocol):
    """The scan's ears pushed 1 mm out along their normals: 1 mm in the ear region, 0 in the
    face sphere, and an alignment that the ears did not move."""
    v, f, lm = ict_mean.vertices, ict_mean.faces, ict_mean.landmark_points
    ears = ict_mean.regions["ears"]
    mesh = v + 1.0 * ears[:, None] * vertex_normals(v, f)
    sc = score(mesh, f, v, f, lm, lm, protocol=protocol)
    np.testing.assert_allclose(sc.matrix, np.eye(4), atol=1e-6)
    for side in (sc.accuracy, sc.completion):
        assert side.mean < 1e-6 and side.count == face_region(v, lm).sum()
    in_ears = ear_region(v, lm)
    for side, per_vertex in ((sc.ears.accuracy, sc.ears.accuracy_per_vertex),
                             (sc.ears.completion, sc.ears.completion_per_vertex)):
        assert side.count == in_ears.sum()
        assert np.isnan(per_vertex[~in_ears]).all()
        # A pushed vertex is at most 1 mm from the other surface, and about 1 mm off
        # (less only in the ear's folds); the rest of the region is untouched.
        assert per_vertex[ears].max() < 1.0 + 1e-6 and np.median(per_vertex[ears]) > 0.95
        assert per_vertex[in_ears & ~ears].max() < 1e-6
        assert side.mean == pytest.approx(np.nanmean(per_vertex))
    assert 0.3 < sc.ears.accuracy.mean < 0.5  # 905 of 2,208 region vertices pushed


def test_a_mesh_without_ears_scores_nan_accuracy_and_poor_completion_there(ict_mean):
    v, f, lm = ict_mean.vertices, ict_mean.faces, ict_mean.landmark_points
    cv, cf = crop(v, f, face_region(v, lm, 1.2))
    sc = score(cv, cf, v, f, lm, lm, protocol="metric")
    assert sc.accuracy.mean < 1e-3
    assert sc.ears.accuracy.count == 0 and math.isnan(sc.ears.accuracy.mean)
    assert np.isnan(sc.ears.accuracy_per_vertex).all()
    assert sc.ears.completion.count == ear_region(v, lm).sum() and sc.ears.completion.mean > 20.0
    doc = score_json(sc)
    assert doc["ears"]["accuracy"]["mean"] is None  # strict JSON: no nan
    json.loads(json.dumps(doc, allow_nan=False))
    line = paper_table([("cropped", [doc])], region="ears").splitlines()[2]
    assert line.startswith("| cropped | 1 | – | – | – | ")


def test_config_is_validated_and_documented():
    with pytest.raises(ValidationError):
        EvaluationConfig(trim=0.0)
    with pytest.raises(ValidationError, match="radius_factor"):
        EvaluationConfig(radius_factor=0.0)  # a sphere of no size
    with pytest.raises(ValidationError, match="radius_factr"):
        EvaluationConfig(radius_factr=1.2)  # a misspelt setting is refused, not ignored
    assert all(fi.description for fi in EvaluationConfig.model_fields.values())


@pytest.mark.parametrize("what", ["mesh", "scan"])
def test_a_mesh_of_degenerate_triangles_is_refused_not_scored(what, head_files, tmp_path):
    """Triangles that are points or lines have no surface: scored, such a mesh made of the
    scan's own vertices would be perfectly accurate (1e-14 mm). Refused for the mesh and
    for the scan; a few degenerate triangles among real ones are not."""
    mesh, scan, scan_lm, mesh_lm = head_files
    vertices = trimesh.load(scan, process=False).vertices
    index = np.arange(len(vertices))
    degenerate = tmp_path / "degenerate.ply"
    trimesh.Trimesh(vertices, np.column_stack([index, index, np.roll(index, 1)]),
                    process=False).export(degenerate)
    files = {"mesh": mesh, "scan": scan, what: degenerate}
    with pytest.raises(InputError) as refused:
        evaluate(files["mesh"], files["scan"], scan_lm)
    assert str(refused.value) == (f"{what} file {degenerate} has no triangle with an area "
                                  "(every one is a point or a line); repair the mesh")
    some = tmp_path / "some.ply"
    head = trimesh.load(scan, process=False)
    trimesh.Trimesh(head.vertices, np.vstack([head.faces, [[0, 0, 0], [1, 1, 2]]]),
                    process=False).export(some)
    assert evaluate(some, scan, scan_lm, protocols=("metric",))["metric"].accuracy.mean < 1e-6


def test_the_stage_writes_the_distance_of_each_scored_vertex_face_and_ears(ict_mean, tmp_path):
    """The evaluation stage's per-vertex accuracy (the capture page's heat map) holds the ear
    region's distances beside the face sphere's: ears pushed 1 mm out read about 1 mm, not
    'not scored'."""
    from facecap_core.evaluation.stage import ACCURACY_NPY, main

    v, f, lm = ict_mean.vertices, ict_mean.faces, ict_mean.landmark_points
    ears = ict_mean.regions["ears"]
    for folder in ("mesh", "scan", "scan_landmarks"):
        (tmp_path / folder).mkdir()
    trimesh.Trimesh(v + 1.0 * ears[:, None] * vertex_normals(v, f), f,
                    process=False).export(tmp_path / "mesh" / "mesh.ply")
    save_landmarks(tmp_path / "mesh" / "mesh_landmarks.json", lm)
    trimesh.Trimesh(v, f, process=False).export(tmp_path / "scan" / "scan.ply")
    save_landmarks(tmp_path / "scan_landmarks" / "scan_landmarks.json", lm)
    main(tmp_path / "mesh", tmp_path / "scan", tmp_path / "out", tmp_path / "scan_landmarks")
    per_vertex = np.load(tmp_path / "out" / ACCURACY_NPY.format(protocol="metric"))
    in_ears, in_face = ear_region(v, lm), face_region(v, lm)
    assert np.isfinite(per_vertex[in_ears | in_face]).all()
    assert np.isnan(per_vertex[~(in_ears | in_face)]).all()
    assert np.median(per_vertex[ears & in_ears]) > 0.95  # the pushed ears, coloured
    assert np.nanmax(per_vertex[in_face]) < 1e-3


def test_the_stage_keeps_the_transform_that_brought_the_mesh_onto_the_scan(ict_mean, tmp_path):
    """The scan is the mesh turned 15° and moved 50 mm: each protocol's kept alignment maps
    the mesh onto it, rigidly for the metric protocol."""
    from facecap_core.evaluation.stage import main, read_alignment
    from facecap_core.fitting.run import MESH_LANDMARKS

    v, f, lm = ict_mean.vertices, ict_mean.faces, ict_mean.landmark_points
    angle = np.radians(15)
    R = np.array([[np.cos(angle), 0, np.sin(angle)], [0, 1, 0],
                  [-np.sin(angle), 0, np.cos(angle)]])
    t = np.array([50.0, -20.0, 10.0])
    for folder in ("mesh", "scan", "scan_landmarks"):
        (tmp_path / folder).mkdir()
    trimesh.Trimesh(v, f, process=False).export(tmp_path / "mesh" / "mesh.ply")
    save_landmarks(tmp_path / "mesh" / MESH_LANDMARKS, lm)
    trimesh.Trimesh(v @ R.T + t, f, process=False).export(tmp_path / "scan" / "scan.ply")
    save_landmarks(tmp_path / "scan_landmarks" / "scan_landmarks.json", lm @ R.T + t)
    main(tmp_path / "mesh", tmp_path / "scan", tmp_path / "out", tmp_path / "scan_landmarks")
    for protocol in ("similarity", "metric"):
        kept = read_alignment(tmp_path / "out", protocol)
        assert np.abs(kept.apply(v) - (v @ R.T + t)).max() < 0.05, protocol
    assert read_alignment(tmp_path / "out", "metric").s == 1.0
    with pytest.raises(InputError, match="holds no alignment"):
        read_alignment(tmp_path / "mesh", "metric")
    # The capture page moves the scan by the kept metric alignment: back onto the mesh.
    from facecap.pages.scan import scan_in_mesh_frame

    on_mesh, _ = scan_in_mesh_frame(tmp_path / "scan" / "scan.ply",
                                    read_alignment(tmp_path / "out", "metric"))
    assert np.abs(on_mesh - v).max() < 0.05


@pytest.mark.parametrize("beside", [True, False], ids=["landmarks-beside", "mesh-alone"])
def test_the_stage_run_by_the_runner_writes_what_its_row_lists(beside, tmp_path):
    """The evaluation stage through the runner (which checks its files against its row), on
    a mesh in the template's topology with its ``landmarks.json`` beside it (the fitting
    stage's artifact) and alone (``evaluate-dataset`` ingests ``mesh.ply`` only): both
    commit exactly the row's files, and a mesh alone is still aligned from the template's
    landmark vertices (the scan is turned 70° and moved 120 mm, too far for ICP alone)."""
    from facecap.tasks.graph import INPUT_VERSION
    from facecap.tasks.runner import ingest, run_stage
    from facecap.tasks.store import input_key, open_store
    from facecap_core.evaluation.stage import EVALUATION_JSON, STAGE
    from facecap_core.fitting.run import MESH_LANDMARKS, MESH_PLY

    template = Template.default()
    v, f, lm = template.vertices, template.faces, template.landmark_points
    R, t = rotation_matrix([0.0, 1.0, 0.0], np.radians(70)), np.array([120.0, -40.0, 60.0])
    files = tmp_path / "files"
    files.mkdir()
    trimesh.Trimesh(v, f, process=False).export(files / MESH_PLY)
    trimesh.Trimesh(v @ R.T + t, f, process=False).export(files / "scan.ply")
    save_landmarks(files / "scan_landmarks.json", lm @ R.T + t)
    store_url = str(tmp_path / "store")
    store = open_store(store_url)
    if beside:
        save_landmarks(files / MESH_LANDMARKS, lm)
        mesh_key = input_key(files / MESH_LANDMARKS)
        store.put(mesh_key, {MESH_PLY: files / MESH_PLY, MESH_LANDMARKS: files / MESH_LANDMARKS},
                  stage="input", inputs={}, config=None, version=INPUT_VERSION)
    else:
        mesh_key = ingest(store_url, files / MESH_PLY, MESH_PLY)
    inputs = {"mesh": mesh_key, "scan": ingest(store_url, files / "scan.ply", "scan.ply"),
              "scan_landmarks": ingest(store_url, files / "scan_landmarks.json",
                                       "scan_landmarks.json")}
    key, computed = run_stage(store_url, STAGE, inputs, EvaluationConfig())
    assert computed
    folder = store.get(key)
    written = sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*")
                     if p.is_file() and p.name != "manifest.json")
    assert written == sorted((*STAGE.outputs, *STAGE.optional_outputs))
    scores = json.loads((folder / EVALUATION_JSON).read_text())
    for protocol in ("similarity", "metric"):
        assert scores[protocol]["accuracy"]["median"] < 0.05, protocol
