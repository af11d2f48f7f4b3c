"""Fusion of depth maps: exact maps land on the surface, an inconsistent one is left out."""

from __future__ import annotations

import numpy as np

from facecap_core.evaluation import distances
from facecap_core.fitting.run import load_cloud_errors
from facecap_core.mvs import (
    DepthMap,
    fuse,
    write_ply,
)
from facecap_core.render import RaycastScene


def _gt_map(view, scene, offset_mm=0.0):
    scn = RaycastScene()
    scn.add(scene["V"], scene["F"])
    hits = scn.cast_camera(view.intr, view.R, view.t)
    fn = np.cross(scene["V"][scene["F"][:, 1]] - scene["V"][scene["F"][:, 0]],
                  scene["V"][scene["F"][:, 2]] - scene["V"][scene["F"][:, 0]])
    fn /= np.linalg.norm(fn, axis=1, keepdims=True)
    n = np.zeros(hits.depth.shape + (3,), np.float32)
    n_cam = fn[hits.triangle[hits.valid]] @ view.R.T
    n_cam *= np.where(n_cam[:, 2] > 0, -1, 1)[:, None]
    n[hits.valid] = n_cam
    depth = np.where(hits.valid, hits.depth + offset_mm, 0).astype(np.float32)
    return DepthMap(view.index, depth, n, np.zeros_like(depth), view.intr, view.R, view.t)


def test_fusing_exact_depth_maps_lands_on_the_surface(scene, tmp_path):
    views = scene["views"]
    maps = [_gt_map(v, scene) for v in views]
    cloud = fuse(maps, [v.rgb for v in views], min_consistent_views=2)
    assert len(cloud) > 5000
    d = distances(cloud.points, scene["V"], scene["F"])
    assert np.median(d) < 0.02 and np.percentile(d, 99) < 0.1
    assert np.all(cloud.views >= 3)
    assert np.allclose(np.linalg.norm(cloud.normals, axis=1), 1.0)
    # Exact maps agree to the float32 depth's rounding: no spread between the views.
    assert np.median(cloud.spread) < 0.005
    path = write_ply(cloud, tmp_path / "cloud.ply")
    import open3d as o3d
    back = o3d.io.read_point_cloud(str(path))
    assert len(back.points) == len(cloud) and back.has_normals() and back.has_colors()
    points, normals, errors = load_cloud_errors(path)
    assert np.allclose(points, cloud.points) and normals is not None
    assert np.allclose(errors, cloud.spread / np.sqrt(cloud.views), atol=1e-6)

    # Views 0.3 mm in front of and behind the surface in turn: each fused point's spread is
    # the sample standard deviation of its views' depths along its normal, which the rays
    # meet at up to ~45° here: between 0.3 cos 45° and 0.3 × sqrt(k / (k - 1)).
    shifted = [_gt_map(v, scene, offset_mm=0.3 if k % 2 else -0.3) for k, v in enumerate(views)]
    mixed = fuse(shifted, None, min_consistent_views=2)
    both = mixed.spread[mixed.views >= 4]  # seen from both kinds of view (k >= 4)
    assert 0.18 < np.median(both) < 0.35, np.median(both)

    # A map 4 mm off everywhere agrees with no other view: none of its depths are fused.
    outlier = _gt_map(views[3], scene, offset_mm=4.0)
    cloud2 = fuse(maps[:3] + [outlier] + maps[4:], None, min_consistent_views=2)
    d2 = distances(cloud2.points, scene["V"], scene["F"])
    # (Near view 3's silhouette the 4 mm shift runs almost along the surface, so a few of
    # its points legitimately agree; measured max 0.43 mm.)
    assert np.median(d2) < 0.02 and d2.max() < 1.0


def test_the_views_check_keeps_what_the_other_views_confirm_on_any_thread_count(scene):
    """The check of each map against the others (the fusion's first step): exact maps keep
    most of their depths (those of the sweep's end views fewer: less of what they see is
    seen by two others), a map 4 mm off almost none, and maps checked two at a time are the
    same maps, to the bit, as one at a time."""
    from facecap_core.mvs import geometric_filter

    views = scene["views"]
    maps = [_gt_map(v, scene) for v in views]
    maps[3] = _gt_map(views[3], scene, offset_mm=4.0)
    one, two = (geometric_filter(maps, 2, 1.0, 1.0, 30.0, threads=t) for t in (1, 2))
    kept = [np.count_nonzero(m.depth) / max(np.count_nonzero(o.depth), 1)
            for m, o in zip(one, maps, strict=True)]
    exact = [k for i, k in enumerate(kept) if i != 3]
    assert np.median(exact) > 0.85 and min(exact) > 0.6, kept
    assert kept[3] < 0.05, kept  # near its silhouette a few depths run along the surface
    for a, b in zip(one, two, strict=True):
        assert a.index == b.index
        assert np.array_equal(a.depth, b.depth) and np.array_equal(a.normal, b.normal)
