"""Reference reconstructions that need no video, scored with the same protocol as facecap.

"Mean template": the template as it is, aligned to the scan by its landmarks and trimmed ICP
(the paper's "Mean Basel" row). Under the similarity protocol it may scale; under the metric
protocol it keeps its own millimetres.
"""

from __future__ import annotations

from pathlib import Path

from facecap_core.evaluation import PROTOCOLS, Score, error_heatmap, score
from facecap_core.meshio import load_landmarks, load_mesh
from facecap_core.template import Template


def mean_template(template: Template, scan_path: str | Path, scan_landmarks_path: str | Path,
                  protocols=PROTOCOLS, heatmap_dir: str | Path | None = None
                  ) -> dict[str, Score]:
    """Score the unmodified template against a scan under each protocol."""
    scan = load_mesh(scan_path, "scan")
    scan_lm = load_landmarks(scan_landmarks_path)
    scores = {p: score(template.vertices, template.faces, scan.vertices, scan.faces, scan_lm,
                       template.landmark_points, protocol=p) for p in protocols}
    if heatmap_dir is not None:
        for p, s in scores.items():
            error_heatmap(s.alignment.apply(template.vertices), template.faces,
                          s.accuracy_per_vertex, Path(heatmap_dir) / f"mean_template_{p}.png")
    return scores
