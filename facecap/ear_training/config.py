"""The settings of the ear models' training (``facecap train-ears --config``)."""

from __future__ import annotations

from pathlib import Path

from pydantic import Field, model_validator

from facecap_core.config import StrictModel


class EarTrainingConfig(StrictModel):
    """Training set (renders of ICT identities) and training of the ear detector (dlib HOG)
    and ear-contour shape predictor (dlib ERT) (``facecap/ear_training/``)."""

    ict_model: Path | None = None
    """ICT Face Model Light ``.npz``; default ``$FACECAP_ICT_MODEL``."""
    contour_points: int = Field(12, ge=4, le=40)
    """Points on each ear's outer contour (template vertices, helix root to lobe)."""
    contour_arc_deg: tuple[float, float] = (130.0, -115.0)
    """Start and end of the contour as angles around the ear's centre seen from the side
    (0 = straight back, 90 = up, -90 = down), swept clockwise over the back of the ear."""
    identities: int = Field(80, ge=1, le=5000)
    """ICT identities rendered."""
    first_identity_seed: int = Field(100, ge=2, le=2**32 - 1)
    """Seed of the first identity (seeds 0 and 1 are held out for evaluation)."""
    identity_sigma: float = Field(1.0, ge=0, le=3)
    """Spread of the identity coefficients, in model standard deviations."""
    views_per_identity: int = Field(15, ge=1, le=1000)
    """Usable views kept per identity (sides drawn at random; right ears are mirrored)."""
    image_size: int = Field(360, ge=96, le=2048)
    """Square render size in pixels."""
    yaw_deg: tuple[float, float] = (30.0, 100.0)
    """Range of the camera's yaw around the head (0 = frontal, 90 = profile)."""
    elevation_deg: tuple[float, float] = (-15.0, 20.0)
    """Range of the camera's elevation above the eye plane."""
    roll_deg: float = Field(10.0, ge=0, le=45)
    """Largest camera roll either way."""
    distance_mm: tuple[float, float] = (300.0, 550.0)
    """Range of the camera's distance to the head's centre (perspective as in a capture)."""
    ear_height_px: tuple[float, float] = (75.0, 170.0)
    """Range of the ear contour's image height; the focal length is set to give it."""
    min_visible_fraction: float = Field(0.6, ge=0, le=1)
    """A view is kept when at least this fraction of its contour points is visible."""
    hair_probability: float = Field(0.6, ge=0, le=1)
    """Fraction of views with hair painted around the ears (random hairline, colour)."""
    rooms: int = Field(6, ge=1, le=100)
    """Random textured rooms (backgrounds) shared among the identities."""
    box_aspect: float = Field(0.75, gt=0.2, le=2)
    """Width / height of the ear boxes (fixed: HOG scans one window shape)."""
    box_padding: float = Field(0.15, ge=0, le=1)
    """Margin added on each side of the contour's extent, as a fraction of the box height."""
    detector_window_px: int = Field(80, ge=24, le=256)
    """Height of the HOG detection window (its width follows ``box_aspect``)."""
    detector_c: float = Field(30.0, gt=0)
    """SVM regularisation C of the HOG detector (larger: fits the training set harder)."""
    detector_epsilon: float = Field(0.01, gt=0)
    """Stopping tolerance of the detector's SVM solver."""
    predictor_cascade_depth: int = Field(10, ge=1, le=30)
    """Cascade levels of the shape predictor."""
    predictor_tree_depth: int = Field(4, ge=1, le=8)
    """Depth of each regression tree."""
    predictor_trees_per_level: int = Field(120, ge=1, le=2000)
    """Regression trees per cascade level (with the depth, sets the model file's size)."""
    predictor_nu: float = Field(0.1, gt=0, le=1)
    """Shrinkage (learning rate) of the tree ensemble."""
    predictor_oversampling: int = Field(20, ge=1, le=200)
    """Random initial shapes per training sample."""
    predictor_translation_jitter: float = Field(0.1, ge=0, le=1)
    """Random shifts of the training boxes (fraction of the box size): robustness to the
    detector's box placement."""
    predictor_feature_pool_size: int = Field(400, ge=10, le=5000)
    """Pixel samples per cascade level from which split features are drawn."""
    predictor_test_splits: int = Field(20, ge=1, le=500)
    """Random splits tried per tree node."""
    threads: int = Field(2, ge=1, le=256)
    """Threads for dlib's training."""
    seed: int = Field(0, ge=0, le=2**32 - 1)
    """Seed of every random draw (views, rooms, lights, noise, the predictor's trainer)."""

    @model_validator(mode="after")
    def _check_ranges(self):
        for name in ("yaw_deg", "elevation_deg", "distance_mm", "ear_height_px"):
            lo, hi = getattr(self, name)
            if lo > hi:
                raise ValueError(f"{name}: lower bound {lo} exceeds upper bound {hi}")
        if self.contour_arc_deg[0] <= self.contour_arc_deg[1]:
            raise ValueError("contour_arc_deg: the start angle must exceed the end angle")
        return self
