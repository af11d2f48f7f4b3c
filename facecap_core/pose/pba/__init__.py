"""Photometric bundle adjustment (PBA) of keyframe poses, intrinsics and radial distortion.

Its modules share one parameter layout (the intrinsics, then pose and brightness per
keyframe after the first; :data:`.kernels.N_INTR`, :data:`.kernels.N_FRAME`):

* :mod:`.kernels`: the numba kernel of the photometric residuals, their Jacobians and the
  Schur-reduced normal equations, and the pixel model it inlines;
* :mod:`.normal`: that kernel summed on threads, the tracked points' kernel, the
  back-substitution, the scale gauge, the pose increments, the camera velocities and the
  adjustment to the tracks alone;
* :mod:`.problem`: :class:`PBAConfig` and what the solve is over (:class:`.problem.Problem`:
  images, points and their initial depths, targets, tracks, priors, timing);
* :mod:`.solve`: a level of the image pyramid (the normal equations at a state, the models'
  choice, the Levenberg-Marquardt iterations) and :func:`photometric_bundle_adjustment`,
  which runs the levels coarse to fine.

The method of DSO (Engel et al.), run as a batch over all keyframes:

* **Points**: the initial reconstruction's sparse points, each hosted in the middle keyframe
  of its track at its depth (default), or in every keyframe the strongest-gradient pixel of
  each ``cell``×``cell`` block with an epipolar depth search; an 8-pixel pattern around each;
  one unknown per point, its inverse depth along the host ray.
* **Residuals**: each pattern pixel is cast along its host ray at the point's inverse depth,
  projected into nearby keyframes (the targets) and compared there:
  ``r = I_t(u_t) - b_t - exp(a_t - a_h) (I_h(u_h) - b_h)``, with a per-keyframe affine
  brightness (a, b) for exposure changes, DSO's gradient-dependent weight and a robust loss
  scaled to the residuals' own spread (whole patterns dropped as outliers). Each side is
  sampled along the other keyframe's motion-blur streak, and optionally each row at its own
  time (rolling shutter).
* **Tracked points** (optional, the default in the pose stage): the initial reconstruction's
  points (3 unknowns each) and their reprojection errors against their observations, in the
  same solve.
* **Unknowns**: every keyframe's pose (6) and brightness (2), one shared camera: focal length,
  principal point and radial distortion k1, k2 (5), all inverse depths and tracked points.
* **Solver**: Levenberg–Marquardt with analytic Jacobians. Inverse depths (1×1 blocks) and
  tracked points (3×3 blocks) are eliminated by the Schur complement, leaving a small dense
  system over the camera unknowns; coarse to fine over an image pyramid.
* **Gauge**: the first keyframe's pose and brightness are fixed, and the scale by a prior on
  the distance between the first two camera centres. Optionally the camera centres are held
  near the start by a prior; without tracked points the intrinsics are held (see
  :class:`PBAConfig`).

Distortion is part of the model (rays are undistorted with the current k1, k2), so the
intrinsics' Jacobians pass through the undistortion by the implicit-function theorem.
"""

from facecap_core.pose.pba.normal import camera_motion
from facecap_core.pose.pba.problem import PBAConfig
from facecap_core.pose.pba.solve import PBAResult, photometric_bundle_adjustment

__all__ = ["PBAConfig", "PBAResult", "camera_motion", "photometric_bundle_adjustment"]
