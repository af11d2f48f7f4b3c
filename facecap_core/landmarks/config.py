"""The landmark stage's settings (:class:`LandmarkConfig`), in a module of their own: the stage
and the modules it runs (:mod:`.iris`) read them, and none of those imports the stage."""

from __future__ import annotations

from pydantic import Field, model_validator

from facecap_core.config import StrictModel
from facecap_core.pose.stage import MIN_YAW_SPAN_DEG


class LandmarkConfig(StrictModel):
    """68-point landmarks per keyframe, their gate, and 3D triangulation
    (``facecap_core/landmarks/stage.py``, where this class is imported from too; Agrawal et
    al. 2020, "Landmark constraints")."""

    min_detector_score: float = Field(0.5, ge=0.1, le=1)
    """Weakest face detection kept (MediaPipe's face detector score, 0.1-1: 0.8-0.9 on faces
    turned up to 50°; ``facecap_core/face.py``)."""
    gate_max_yaw_deg: float = Field(40.0, gt=0, le=90)
    """Gate: largest yaw of the camera around the head (from the first triangulation): the
    detector's points grow less certain beyond it."""
    gate_max_reprojection: float = Field(0.02, gt=0, le=1)
    """Gate: largest median reprojection error of a keyframe's inner points against the
    landmarks triangulated from all views, as a fraction of its face box size (the square
    root of the box area; ~0.005 for a good detection)."""
    convention_correction: bool = True
    """Move the triangulated points from the detector's image convention to 3D landmarks on
    the face (calibrated per-landmark offsets, ``facecap_core/landmarks/convention.py``)."""
    max_point_spread: float = Field(0.03, gt=0)
    """A 3D landmark is dropped (null) when its standard deviation along its least certain
    direction, for the median reprojection error, exceeds this fraction of the eye-centre
    distance (~2 mm): its inlier views are too alike."""
    min_views: int = Field(3, ge=2, le=100)
    """Fewest gated keyframes wanted; with fewer the gate widens to the best-agreeing
    detections (recorded in landmarks2d.json)."""
    outlier_threshold: float = Field(0.02, gt=0, le=1)
    """A view's observation of a point is an outlier above this reprojection error, as a
    fraction of that view's face box size."""
    huber: float = Field(0.01, gt=0, le=1)
    """Huber threshold of the robust refinement, same unit as ``outlier_threshold``."""
    min_parallax_deg: float = Field(2.0, ge=0, le=45)
    """Two views start a point's hypothesis only when their rays meet at this angle or more."""
    ear_min_yaw_deg: float = Field(45.0, ge=0, le=180)
    """Ears are searched in keyframes at least this far from frontal (profile side) ..."""
    ear_max_yaw_deg: float = Field(100.0, ge=0, le=180)
    """... and at most this far."""
    min_yaw_span_deg: float = Field(MIN_YAW_SPAN_DEG, ge=0, le=360)
    """Fewest degrees of yaw around the head that the registered keyframes must span (the
    face's sides are seen from ±20° on; with less, depth from the frontal views alone is too
    ill-conditioned for a metric face). A full capture spans about 180°."""
    irises: bool = True
    """Measure the irises (pupil centres, horizontal iris diameter) in the frontal keyframes
    from the face mesh's iris points (``facecap_core/landmarks/iris.py``): the coarse stage's
    IPD and iris-size scale cues."""
    iris_max_yaw_deg: float = Field(15.0, gt=0, le=60)
    """Irises are measured in gated keyframes at most this far from frontal: beyond, the iris
    is foreshortened and MediaPipe's diameter less certain (on the calibration renders, 15°
    gave a 4.7 % spread of the measured diameter and 0.2 % of the pupil distance; 35°: 4.8 %
    and 0.5 %)."""
    min_eye_opening: float = Field(0.2, ge=0, le=1)
    """An eye is measured only when its lids are this far apart, as a fraction of its
    corner-to-corner width (the eye aspect ratio of blink detection, from the face mesh's lid
    points): the lids of a half-closed eye cut the iris. Measured: 0.26-0.30 on rendered open
    eyes (ICT identity 11, calibration renders), 0.06-0.17 on the closed eyes of
    ``photo_set_31``."""
    ear_min_views: int = Field(3, ge=2, le=100)
    """Fewest keyframes with an ear detection for that ear's points to be triangulated."""
    ear_outlier_threshold: float = Field(0.1, gt=0, le=1)
    """An ear point's observation is an outlier above this reprojection error, as a fraction
    of the ear box diagonal (the ear predictor's error is ~0.05 of it)."""
    ear_huber: float = Field(0.03, gt=0, le=1)
    """Huber threshold of the ears' robust refinement, same unit."""

    @model_validator(mode="after")
    def _check_ranges(self):
        if self.ear_min_yaw_deg > self.ear_max_yaw_deg:
            raise ValueError("ear_min_yaw_deg exceeds ear_max_yaw_deg")
        if self.huber > self.outlier_threshold:
            raise ValueError("huber must not exceed outlier_threshold")
        return self
