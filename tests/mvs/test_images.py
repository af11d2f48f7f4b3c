"""The prepared keyframes a process keeps for its depth maps."""

from __future__ import annotations

import numpy as np


def test_a_prepared_view_is_kept_until_its_file_or_camera_changes(tmp_path, monkeypatch):
    import cv2

    from facecap_core.camera import CameraSet, Intrinsics
    from facecap_core.frames import frame_name
    from facecap_core.mvs import images

    rng = np.random.default_rng(0)
    for i in (3, 4):
        cv2.imwrite(str(tmp_path / frame_name(i)), rng.integers(0, 255, (90, 160, 3), np.uint8))
    cams = CameraSet(Intrinsics(160, 90, 150.0, 150.0, 79.5, 44.5, -0.1, 0.0), [3, 4],
                     np.stack([np.eye(3)] * 2), np.zeros((2, 3)))
    first = images.load_view(tmp_path, cams, 3, 160)
    assert images.load_view(tmp_path, cams, 3, 160) is first
    assert images.load_view(tmp_path, cams, 3, 80) is not first  # another width
    moved = CameraSet(cams.intrinsics, [3, 4], cams.R, cams.t + 1.0)
    assert np.array_equal(images.load_view(tmp_path, moved, 3, 160).t, [1.0, 1.0, 1.0])
    # A keyframe written again (another run's frames in the same folder) is read again.
    cv2.imwrite(str(tmp_path / frame_name(3)), np.zeros((90, 160, 3), np.uint8))
    again = images.load_view(tmp_path, cams, 3, 160)
    assert again is not first and again.grey.max() == 0
    # The cache holds at most its bytes: with room for one view, the older one goes.
    monkeypatch.setattr(images, "VIEW_CACHE_BYTES", again.rgb.nbytes + again.grey.nbytes)
    images.load_view(tmp_path, cams, 4, 160)
    assert images.load_view(tmp_path, cams, 3, 160) is not again
