"""Non-rigid template fitting (Agrawal et al. 2020, "Mesh fitting").

Optimal-step NICP (Amberg et al. 2007) deforms the template — never its topology — onto a
fused MVS point cloud (normal-ray median targets), the 51 inner 3D landmarks (+ optional ear
points) and keyframe silhouettes (Canny edges), with a stiffness that relaxes from global to
local while the landmark weights fall. See docs/fitting.md.

    from facecap_core.fitting import fit, fit_and_write, Keyframe
    result = fit(Template.default(), cloud, landmarks, keyframes)   # FitResult
    fit_and_write(cloud, landmarks, "out/fit")                                 # -> out/fit/mesh.ply
"""

from facecap_core.fitting.run import fit_and_write, keyframes_from_video, load_cloud, write_mesh
from facecap_core.fitting.settings import FittingConfig
from facecap_core.nonrigid.constraints import Keyframe, cloud_targets, edge_targets
from facecap_core.nonrigid.nicp import FitResult, check_inputs, fit
from facecap_core.nonrigid.solver import NicpSystem

__all__ = ["Keyframe", "FitResult", "FittingConfig", "NicpSystem", "fit", "fit_and_write",
           "write_mesh", "load_cloud", "keyframes_from_video", "check_inputs",
           "cloud_targets", "edge_targets"]
