"""Dense multi-view stereo (the paper's "Point cloud generation" stage).

View selection (:mod:`.views`), keyframe preparation (:mod:`.images`), the coarse-mesh prior
(:mod:`.prior`), PatchMatch depth/normal maps (:mod:`.patchmatch`), filtering
(:mod:`.filtering`), fusion (:mod:`.fusion`), and the three stages the service runs, view
selection, one depth map per keyframe and fusion (:mod:`.stage`).
"""

from facecap_core.mvs.filtering import filter_with_prior, geometric_filter
from facecap_core.mvs.fusion import PointCloud, fuse, write_ply
from facecap_core.mvs.images import MVSView, prepare_view
from facecap_core.mvs.patchmatch import DepthMap, patchmatch_depth
from facecap_core.mvs.prior import CoarsePrior, coarse_prior
from facecap_core.mvs.stage import (
    choose_sources,
    compute_depth_map,
    save_depth_map,
    sparse_from_mesh,
)
from facecap_core.mvs.views import gaussian_score, pair_scores, select_sources, visible_points

__all__ = [
    "CoarsePrior", "DepthMap", "MVSView", "PointCloud", "choose_sources", "coarse_prior",
    "compute_depth_map", "filter_with_prior", "fuse", "gaussian_score", "geometric_filter",
    "pair_scores", "patchmatch_depth", "prepare_view", "save_depth_map", "select_sources",
    "sparse_from_mesh", "visible_points", "write_ply",
]
