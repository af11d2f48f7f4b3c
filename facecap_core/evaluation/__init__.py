"""Geometric accuracy of a face mesh against a ground-truth scan (Agrawal et al. 2020, Table 1).

Protocol
--------
1. **Face region.** Both the reconstruction and the ground-truth scan usually hold more than
   the face (ears, neck, hair, a back of the head), and the amount differs from method to
   method. The headline scores are therefore taken inside one sphere defined on the *scan*,
   in the style of the NoW benchmark: its centre is the scan's nose tip (iBUG landmark 30)
   and its radius is ``radius_factor * (|L36 - L45| + |L27 - L33|) / 2`` — the mean of the
   outer-eye-corner distance and the nasion–nose-base length, times ``radius_factor`` (1.4 by
   default, about 95 mm on an adult face: ear to ear across the front, forehead to chin). See
   :func:`region_sphere` and :func:`face_region`.

   **Ear region**, scored beside it: the ears and the sides of the head around them, which the
   face sphere leaves out. Around each ear a sphere, also defined on the scan's landmarks in
   units of the same face size ``(|L36 - L45| + |L27 - L33|) / 2``: its centre lies
   ``EAR_CENTRE_OFFSET`` = (0.072, -0.375, -0.5) face sizes (outwards, up, forwards) from the
   top of the jaw contour on its side (L16 for the subject's left ear, L0 for the right) in the
   landmarks' head frame (eye centre to eye centre, chin to nasion, out of the face), and its
   radius is ``EAR_RADIUS_FACTOR`` = 0.78 face sizes (≈ 55 mm). The ear region is the inside
   of either ear sphere *outside* the face sphere, so the two regions are disjoint. The
   constants are calibrated by ``tools/calibrate_ear_region.py`` on ICT identities
   1000–1199, which no benchmark evaluates: the offset is the mean centre of their ears' boxes,
   the radius holds every point of all 400 of their ears (the ear vertices of
   :func:`facecap_core.template.region_masks` and the ear contour of ``ear_contour.json``)
   with at least 0.15 face sizes (≈ 10 mm) to spare; that margin also absorbs a few mm of
   error in L0 / L16. See :func:`ear_spheres` and
   :func:`ear_region`, and docs/evaluation.md for the figures.
2. **Alignment** (:func:`align`). The reconstruction is brought into the scan's frame:

   a. if landmarks of the reconstruction are given, a Umeyama fit of its 51 inner landmarks
      (17–67; the jaw contour 0–16 is not anatomically stable) to the scan's; otherwise the
      identity (the mesh must already be roughly in the scan frame);
   b. trimmed ICP: the mesh vertices inside the face sphere (enlarged ×1.1 so that the
      boundary does not bias the fit) are matched to their closest points *on the scan
      surface* (point-to-triangle), the worst ``1 - trim`` of the matches are dropped, and the
      total transform from the original mesh coordinates to the matched points is re-solved
      (Umeyama) until it stops changing. Anderson acceleration extrapolates the transform
      from the last few steps (same fixed points, several times fewer iterations on smooth
      faces where point-to-point ICP slides slowly).

   Two protocols differ only in the transform allowed. ``"similarity"`` also fits a scale, as
   for methods whose output has no metric scale; ``"metric"`` fixes the scale to 1, so a
   wrongly-sized metric reconstruction is penalised — the point of a metric pipeline.
3. **Distances** (:func:`score`), exact point-to-triangle distances in the scan's millimetres:

   * *accuracy*: from each aligned mesh vertex inside the sphere to the scan surface;
   * *completion*: from each scan vertex inside the sphere to the aligned mesh surface.

   Each side is summarised by mean, std, median and the fractions under 1 mm and 2 mm.
   Accuracy punishes wrong geometry; completion punishes missing geometry (a mesh cropped to
   the nose and eyes can be accurate but is incomplete). The same two are measured in the ear
   region (``Score.ears``), after the same alignment; a region that holds no vertex of one
   side scores nan there.

:func:`paper_table` averages per-capture scores over captures as Table 1 does (see there),
and :func:`error_heatmap` paints per-vertex errors on the mesh for a figure.

Conventions: meshes are in millimetres, the face looks towards +z, +y is up and +x is the
subject's left (the convention of facecap's data and of :func:`error_heatmap`'s views).
"""

from facecap_core.evaluation.alignment import (
    PROTOCOLS,
    Alignment,
    Protocol,
    align,
    distances,
)
from facecap_core.evaluation.consistency import split_half_distance
from facecap_core.evaluation.figures import (
    COLORBAR_HEIGHT,
    error_heatmap,
    mesh_render,
    render_views,
)
from facecap_core.evaluation.region import (
    EAR_CENTRE_OFFSET,
    EAR_RADIUS_FACTOR,
    ear_region,
    ear_spheres,
    face_region,
    face_size,
    region_sphere,
)
from facecap_core.evaluation.scoring import (
    REGIONS,
    RegionScore,
    Score,
    Stats,
    evaluate,
    paper_table,
    score,
    score_json,
)
from facecap_core.evaluation.settings import EvaluationConfig
from facecap_core.evaluation.stage import EVALUATION_JSON, find_file, main

__all__ = [
    "COLORBAR_HEIGHT", "EAR_CENTRE_OFFSET", "EAR_RADIUS_FACTOR", "EVALUATION_JSON", "PROTOCOLS",
    "REGIONS", "Alignment", "EvaluationConfig", "Protocol", "RegionScore", "Score", "Stats",
    "align", "distances", "ear_region", "ear_spheres", "error_heatmap", "evaluate",
    "face_region", "face_size", "find_file", "main", "mesh_render", "paper_table",
    "region_sphere", "render_views", "score", "score_json", "split_half_distance",
]
