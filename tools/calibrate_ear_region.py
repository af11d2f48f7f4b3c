"""Calibrate the ear region of the evaluation (facecap_core/evaluation/region.py).

    python tools/calibrate_ear_region.py [--ict-model PATH] [--seeds 1000 1199]
                                         [--margin 0.15] [--check 0 1 3]

The ear spheres are placed from the scan's 68 landmarks alone: a centre at a fixed offset
from the top of the jaw contour (L16 / L0) in the landmarks' head frame, and a radius, both in
face sizes (``face_size``). The constants come from ICT Face Model identities that no
benchmark evaluates: seeds 1000-1199 (the benchmarks use ICT 0, 1, 3 and the scan "james"),
each drawn as ``ict:SEED`` is (``facecap.synthetic.subjects.ict_subject``).

Per identity and side, the ear is its points in the normalised ear frame (outwards, up,
forwards from the side's anchor, divided by the face size): the ear vertices of the landmark
region masks (``facecap_core.template.region_masks``: the thin flap behind the jaw top) and
the 12 points of the ear's outer contour (``ear_contour.json``, which reaches the lobe
below the masks' band). Then

* offset = mean over identities and both sides of the centre of the ear's bounding box;
* radius factor = the largest distance of any ear point from its predicted centre, over all
  identities and sides, plus ``--margin`` face sizes of the side of the head around the ear,
  rounded up to 0.01.

It prints the constants next to the ones in region.py, and how the region holds the ears of
the calibration identities and of the ``--check`` identities (not used for calibration).
"""

from __future__ import annotations

import argparse
import math
import os
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from facecap.ear_training.contour import SIDES, load_contour_file  # noqa: E402
from facecap_core.assets import packaged_ict_model  # noqa: E402
from facecap_core.evaluation.region import (  # noqa: E402
    EAR_CENTRE_OFFSET,
    EAR_RADIUS_FACTOR,
    ear_spheres,
    face_region,
    face_size,
)
from facecap_core.landmarks.ears import CONTOUR_FILE, MODELS_DIR  # noqa: E402
from facecap_core.template import (  # noqa: E402
    ICT_SKIN_VERTEX_END,
    head_frame,
    ict_identity_vertices,
    ict_skin_faces,
    load_ict_model,
    region_masks,
)

FULL_ICT = Path(__file__).resolve().parents[2] / "shared/data/ict_face_model/ict_face_model.npz"
ANCHOR = {"left": 16, "right": 0}  # the top of the jaw contour beside each ear
OUTWARDS = {"left": 1.0, "right": -1.0}  # head frame +x is the subject's left


def ict_head(model: dict, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Skin vertices (mm) and 68 landmarks of ``ict:SEED``: the coefficients ict_subject draws."""
    coefficients = np.random.default_rng([seed, 1]).standard_normal(100)
    v = ict_identity_vertices(model, coefficients)[:ICT_SKIN_VERTEX_END]
    return v, v[model["landmarks68"]]


def ear_points(model: dict, contour: dict, seed: int) -> tuple[dict, np.ndarray, np.ndarray]:
    """Per side, the ear's points (mm); and the head's vertices and landmarks."""
    v, lm = ict_head(model, seed)
    ears = region_masks(v, lm, ict_skin_faces(model))["ears"]
    R, origin = head_frame(lm)
    lateral = (v - origin) @ R[0]
    return {side: np.concatenate([v[ears & (np.sign(lateral) == OUTWARDS[side])],
                                  contour[side].on(v)])
            for side in SIDES}, v, lm


def in_ear_frame(points: np.ndarray, lm: np.ndarray, side: str) -> np.ndarray:
    """Points in face sizes from the side's anchor along (outwards, up, forwards)."""
    R, _ = head_frame(lm)
    p = (points - lm[ANCHOR[side]]) @ R.T / face_size(lm)
    p[:, 0] *= OUTWARDS[side]
    return p


def reach(points: np.ndarray, lm: np.ndarray, side: str, offset: np.ndarray) -> float:
    """The farthest ear point from the predicted centre, in face sizes."""
    return float(np.linalg.norm(in_ear_frame(points, lm, side) - offset, axis=1).max())


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ict-model", default=os.environ.get("FACECAP_ICT_MODEL") or
                    (str(FULL_ICT) if FULL_ICT.is_file() else str(packaged_ict_model())))
    ap.add_argument("--seeds", nargs=2, type=int, default=[1000, 1199], metavar=("FIRST", "LAST"))
    ap.add_argument("--margin", type=float, default=0.15)
    ap.add_argument("--check", nargs="*", type=int, default=[0, 1, 3])
    args = ap.parse_args(argv)
    model = load_ict_model(args.ict_model)
    contour = load_contour_file(MODELS_DIR / CONTOUR_FILE)["ict"]
    seeds = range(args.seeds[0], args.seeds[1] + 1)
    if set(seeds) & set(args.check):
        raise SystemExit("the checked identities must not be calibration identities")

    heads = {seed: ear_points(model, contour, seed) for seed in seeds}
    centres = np.array([(lambda p: (p.min(0) + p.max(0)) / 2)(in_ear_frame(ears[side], lm, side))
                        for ears, _, lm in heads.values() for side in SIDES])
    offset = centres.mean(0).round(3)
    reaches = np.array([reach(ears[side], lm, side, offset)
                        for ears, _, lm in heads.values() for side in SIDES])
    radius_factor = math.ceil((reaches.max() + args.margin) * 100 - 1e-9) / 100
    sizes = np.array([face_size(lm) for _, _, lm in heads.values()])

    print(f"ICT model {args.ict_model} ({len(model['identity_basis'])} identity modes); "
          f"calibration identities ict:{seeds[0]}-{seeds[-1]} ({len(seeds)}), both ears")
    print(f"face size {sizes.min():.1f}-{sizes.max():.1f} mm (mean {sizes.mean():.1f})")
    print(f"ear-box centre, face sizes (outwards, up, forwards): mean {offset.tolist()}, "
          f"std {centres.std(0).round(3).tolist()}")
    print(f"farthest ear point from the predicted centre: max {reaches.max():.3f}, mean "
          f"{reaches.mean():.3f}, 95th percentile {np.percentile(reaches, 95):.3f} face sizes")
    print(f"radius factor {reaches.max():.3f} + margin {args.margin} -> {radius_factor:.2f} "
          f"({radius_factor * sizes.min():.0f}-{radius_factor * sizes.max():.0f} mm)")
    print(f"region.py: EAR_CENTRE_OFFSET {EAR_CENTRE_OFFSET.tolist()}, EAR_RADIUS_FACTOR "
          f"{EAR_RADIUS_FACTOR}"
          + ("" if np.allclose(offset, EAR_CENTRE_OFFSET) and radius_factor == EAR_RADIUS_FACTOR
             else "  <- differ from the calibration above"))

    def held(seed, ears, v, lm) -> str:
        """How the region of region.py holds one head's ears."""
        centres, radius = ear_spheres(lm)
        points = np.concatenate([ears[s] for s in SIDES])
        margin = min(radius - np.linalg.norm(ears[s] - c, axis=1).max()
                     for s, c in zip(SIDES, centres))
        return (f"ict:{seed}: ear points in the face sphere {face_region(points, lm).sum()}, "
                f"smallest margin to the ear-sphere surface {margin:.1f} mm")

    worst = min(heads, key=lambda s: min(
        EAR_RADIUS_FACTOR - reach(heads[s][0][side], heads[s][2], side, EAR_CENTRE_OFFSET)
        for side in SIDES))
    in_face = sum(face_region(np.concatenate(list(e.values())), lm).sum()
                  for e, _, lm in heads.values())
    print(f"calibration: ear points in the face sphere {in_face}; tightest {held(worst, *heads[worst])}")
    for seed in args.check:
        print("check " + held(seed, *ear_points(model, contour, seed)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
