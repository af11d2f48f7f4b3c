"""The evaluation stage's settings: the protocol that aligns a mesh to its scan and scores
it (:mod:`facecap_core.evaluation.alignment`, :mod:`facecap_core.evaluation.scoring`)."""

from __future__ import annotations

from pydantic import Field

from facecap_core.config import StrictModel


class EvaluationConfig(StrictModel):
    """Parameters of the evaluation protocol; the defaults reproduce facecap's reported
    numbers. Each changes the scores, so each is part of the evaluation's artifact key."""

    radius_factor: float = Field(1.4, gt=0)
    """Face-sphere radius as a multiple of the mean of the outer-eye-corner distance and the
    nasion–nose-base length (1.4 gives about 95 mm on an adult face)."""

    trim: float = Field(0.9, gt=0, le=1)
    """Fraction of ICP matches kept each iteration, the closest ones; the rest are outliers
    (hair, holes, boundary)."""

    max_iterations: int = Field(60, ge=0)
    """Most ICP iterations; 0 keeps the landmark (or identity) alignment as it is."""

    use_landmarks: bool = True
    """Start ICP from a Umeyama fit of the mesh's landmarks when they are given; when False
    they are ignored and ICP starts from the identity."""

    icp_margin: float = Field(1.1, ge=1)
    """ICP uses mesh vertices inside the face sphere enlarged by this factor, so that vertices
    just outside the scored region still hold the fit at its boundary."""

    anderson: int = Field(5, ge=0)
    """ICP steps remembered by Anderson acceleration; 0 gives plain (slow) point-to-point ICP
    with the same result."""

    tolerance: float = Field(1e-6, gt=0)
    """ICP stops when the RMS motion of the matched vertices between two iterations falls
    below this fraction of the face-sphere radius."""
