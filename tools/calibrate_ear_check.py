"""Calibration of the ear-point checks (``facecap_core.landmarks.ear_check``).

    python tools/calibrate_ear_check.py [--ict-model PATH] [--seeds 1000 1200]

On ICT Face Model identities that no benchmark evaluates (seeds 1000-1199 by default, every
mode drawn at 1 sigma as the synthetic subjects are), the exact ear contour (the shipped
ICT transfer of ``ear_contour.json``) is compared with the template's contour placed on the
identity's exact 68 landmarks, as the check compares a triangulated contour. Prints the mean
and spread of the offset per side, the width ratio's spread, and how many heads the shipped
bounds would drop. Then, on as many heads after them (seeds 1200-1399 by default), what the
shipped check does: how many keep both ears, and how many lose both when the ears are put
20 % too far apart (the failure of a wrong detection scale).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from facecap.ear_training.contour import load_contour_file  # noqa: E402
from facecap_core.landmarks import ear_check  # noqa: E402
from facecap_core.landmarks.ears import MODELS_DIR  # noqa: E402
from facecap_core.template import (  # noqa: E402
    Template,
    head_frame,
    ict_identity_vertices,
    load_ict_model,
)

DEFAULT_ICT = Path(__file__).resolve().parents[2] / "shared/data/ict_face_model/ict_face_model.npz"


def ict_ears(model: dict, contour: dict, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """The exact 68 landmarks and left-then-right ear contour points of ICT identity ``seed``
    (every mode drawn at 1 sigma, as the synthetic subjects are)."""
    V = ict_identity_vertices(model, np.random.default_rng([seed, 1]).standard_normal(100))
    return V[model["landmarks68"]], np.r_[contour["ict"]["left"].on(V),
                                          contour["ict"]["right"].on(V)]


def main() -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ict-model", default=str(DEFAULT_ICT))
    ap.add_argument("--seeds", nargs=2, type=int, default=(1000, 1200))
    args = ap.parse_args()
    template = Template.default()
    contour = load_contour_file(MODELS_DIR / "ear_contour.json")
    model = load_ict_model(args.ict_model)
    ids = np.r_[contour["vertex_ids"]["left"], contour["vertex_ids"]["right"]]
    sides = np.array(["left"] * len(contour["vertex_ids"]["left"])
                     + ["right"] * len(contour["vertex_ids"]["right"]))
    offsets, ratios = {"left": [], "right": []}, []
    for seed in range(*args.seeds):
        L, points = ict_ears(model, contour, seed)
        off, ratio = ear_check.contour_offsets(template, L, ids, points, sides)
        for side in offsets:
            offsets[side].append(off[side])
        ratios.append(ratio)
    result = {}
    for side, rows in offsets.items():
        O = np.array(rows)
        mean, sd = O.mean(0), O.std(0)
        z = ear_check.offset_sigmas(O, side)
        result[side] = {"mean_mm": mean.round(2).tolist(), "spread_mm": sd.round(2).tolist(),
                        "largest_sigmas": round(float(z.max()), 2),
                        "dropped": int(np.sum(z > ear_check.EAR_OFFSET_BOUND))}
    W = np.array(ratios)
    lo, hi = ear_check.EAR_WIDTH_RATIO_BOUNDS
    result["width_ratio"] = {"mean": round(float(W.mean()), 4), "std": round(float(W.std()), 4),
                             "min": round(float(W.min()), 4), "max": round(float(W.max()), 4),
                             "outside_bounds": int(np.sum((W < lo) | (W > hi)))}
    print(f"{args.seeds[1] - args.seeds[0]} identities (seeds {args.seeds[0]}-"
          f"{args.seeds[1] - 1})")
    for key, value in result.items():
        print(f"  {key}: {value}")
    held_out = range(args.seeds[1], 2 * args.seeds[1] - args.seeds[0])
    kept = caught = 0
    for seed in held_out:
        L, points = ict_ears(model, contour, seed)
        doc = {"vertex_ids": ids.tolist(), "sides": sides.tolist(), "points": points.tolist()}
        kept += all(c["used"] for c in ear_check.check_ears(doc, L, template)["checks"].values())
        R, origin = head_frame(L)
        wide = (points - origin) @ R.T
        wide[:, 0] *= 1.2
        doc["points"] = (wide @ R + origin).tolist()
        caught += not ear_check.check_ears(doc, L, template)["vertex_ids"]
    result["held_out"] = {"heads": len(held_out), "both_ears_kept": kept,
                          "ears_20pct_apart_both_dropped": caught}
    print(f"held out (seeds {held_out.start}-{held_out.stop - 1}): {result['held_out']}")
    return result


if __name__ == "__main__":
    main()
