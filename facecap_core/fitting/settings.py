"""The fitting stage's settings: the non-rigid registration's
(:class:`~facecap_core.nonrigid.nicp.NicpConfig`) and what the stage does with the fitted
mesh after it (the photometric refinement, folds relaxed, vertex colours)."""

from __future__ import annotations

from pydantic import Field

from facecap_core.nonrigid.nicp import NicpConfig
from facecap_core.nonrigid.photometric import PhotometricConfig


class FittingConfig(NicpConfig):
    """Non-rigid template fitting: the registration's schedule and terms, then the mesh's
    repair and texture. Distances in mm, weights relative to one cloud target."""

    photometric: PhotometricConfig = PhotometricConfig()
    """After the registration, each vertex moved along its normal to where the keyframes
    agree (``rounds: 0``: not)."""
    relax_folds: bool = True
    """Where the fitted mesh folds over, spikes or cuts through itself (a noisy cloud, a wrong
    ear point), replace its deformation there by a membrane until it is sound
    (``facecap_core/fitting/sanity.py``); the figures before and after go to ``fit.json``."""
    texture: bool = True
    """Colour the fitted mesh from the keyframes (per-vertex colour) when keyframes are given."""
    texture_min_cos: float = Field(0.25, ge=0, le=1)
    """A view colours a vertex only when the vertex faces it at least this much (cos)."""
