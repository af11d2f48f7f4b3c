"""Agreement between two fits of one face, without a scan: the split-half distance.

Two fits of one face from disjoint halves of its views are brought together by a similarity
over the face, and each one's face vertices are measured to the other's surface. What the
two halves do not share is noise (and what one half sees that the other does not), so it
measures the noise without a reference (``benchmarks/bench_real.py --split-half``).
"""

from __future__ import annotations

import numpy as np

from facecap_core.evaluation.alignment import distances
from facecap_core.geometry import umeyama

__all__ = ["split_half_distance"]


def split_half_distance(a_vertices: np.ndarray, b_vertices: np.ndarray, faces: np.ndarray,
                        face: np.ndarray) -> dict:
    """Distances (mm) between two fits of one face in one topology (``face``: (n,) bool,
    the vertices to measure, e.g. :func:`facecap_core.nonrigid.roughness.face_vertices`):
    ``b`` is moved onto ``a`` by the similarity over the face vertices (the halves' scales
    and frames differ), then each side's face vertices are measured to the other's surface;
    median, mean and 95th percentile over both sides, and the similarity's scale."""
    a = np.asarray(a_vertices, float)
    b = np.asarray(b_vertices, float)
    if a.shape != b.shape:
        raise ValueError(f"the fits differ in vertex count ({len(a)} vs {len(b)})")
    s, R, t = umeyama(b[face], a[face], with_scale=True)
    b = s * b @ R.T + t
    d = np.concatenate([distances(a[face], b, faces), distances(b[face], a, faces)])
    return {"median_mm": round(float(np.median(d)), 3), "mean_mm": round(float(d.mean()), 3),
            "p95_mm": round(float(np.percentile(d, 95)), 3), "scale_ratio": round(float(s), 4)}
