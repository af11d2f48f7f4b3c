"""Dense multi-view stereo (the paper's "Point cloud generation" stage), three stages:

* :mod:`.views`: which keyframes get a depth map and their source views (the paper's
  view-selection score); ``views.main`` → ``views.json``;
* :mod:`.depth`: one keyframe's depth map from the coarse mesh's prior (:mod:`.prior`) and
  PatchMatch (:mod:`.patchmatch`, the default) or the plane sweep (:mod:`.sweep`), filtered
  (:mod:`.filtering`); ``depth.main`` →
  ``depth_<index>.npz``;
* :mod:`.fusion`: the consistency filter across maps and the fused cloud; ``fusion.main``
  → ``cloud.ply``.

Keyframe preparation (resize, undistort) is :mod:`.images`.
"""

from facecap_core.mvs.depth import compute_depth_map, save_depth_map
from facecap_core.mvs.filtering import filter_with_prior, geometric_filter
from facecap_core.mvs.fusion import PointCloud, fuse, write_ply
from facecap_core.mvs.images import MVSView, prepare_view
from facecap_core.mvs.patchmatch import DepthMap, patchmatch_depth
from facecap_core.mvs.prior import CoarsePrior, coarse_prior
from facecap_core.mvs.views import (
    choose_sources,
    gaussian_score,
    pair_scores,
    select_sources,
    sparse_from_mesh,
    visible_points,
)

__all__ = [
    "CoarsePrior", "DepthMap", "MVSView", "PointCloud", "choose_sources", "coarse_prior",
    "compute_depth_map", "filter_with_prior", "fuse", "gaussian_score", "geometric_filter",
    "pair_scores", "patchmatch_depth", "prepare_view", "save_depth_map", "select_sources",
    "sparse_from_mesh", "visible_points", "write_ply",
]
