"""Training data for the ear models, and their training (dlib HOG detector + ERT predictor).

No registry package ships an ear model, so facecap renders its own training set:

1. **Ear contour on the template.** The outer contour of each ear is a fixed, ordered list of
   default-template vertices (:func:`template_ear_contour`): seen from the side, the outline of
   the template's ``ears`` region, walked from the helix root (top front) over the top and
   the back of the helix down to the lobe, sampled at equal arc length. Along the outline the
   most lateral vertex is taken, so the points sit on the rim of the helix.
2. **Correspondence.** Training heads are ICT Face Model identities (another topology). The
   template is fitted once to the ICT mean head (:func:`facecap_core.fitting.fit`, cloud +
   68 landmarks) and each fitted contour vertex is snapped to the nearest ICT surface point,
   kept as (triangle corners, barycentrics): every ICT identity shares the topology, so the
   same barycentrics give its contour. Any other mesh (James) gets its own fit
   (:func:`fitted_ear_contour`).
3. **Renders.** ICT identities (seeds from ``first_identity_seed``, never the evaluation seeds
   0 and 1) with procedural skin in a textured room, seen from yaw 30-100 deg on either side
   with random elevation, roll, distance, focal length, lights, exposure, blur, noise and
   JPEG compression, and often hair painted around the ears. Ground truth: the contour
   points projected into the image, with a ray-cast visibility flag, and a fixed-aspect box
   around them. Right-ear views are mirrored so
   one model serves both sides (:func:`facecap_core.landmarks.ears.detect_ears` mirrors a
   right-ear image before detection).
4. **Training.** ``dlib.train_simple_object_detector`` (HOG + linear SVM) on the boxes, then
   ``dlib.train_shape_predictor`` (ensemble of regression trees) on the contour points, with
   the detector's own boxes as its input where the detector finds the ear.

Run ``python -m facecap.ear_training --out DIR``; the folder gets
``ear_detector.svm``, ``ear_predictor.dat``, ``ear_contour.json``, ``training.json`` and a
few preview PNGs. Copy the first three into ``facecap_core/landmarks/models/`` to ship them.
"""

from facecap.ear_training.contour import (
    CONTOUR_FILE,
    DETECTOR_FILE,
    MODEL_FILES,
    PREDICTOR_FILE,
    SIDES,
    fitted_ear_contour,
    load_contour_file,
    template_ear_contour,
)
from facecap.ear_training.render import (
    EarRenderer,
    EarSample,
    draw_views,
    ear_box,
    ict_ear_renderer,
    render_key,
    usable,
    visible_points,
)
from facecap.ear_training.train import draw_contour, main, score_detection, train

__all__ = [
    "CONTOUR_FILE", "DETECTOR_FILE", "MODEL_FILES", "PREDICTOR_FILE", "SIDES", "EarRenderer",
    "EarSample", "draw_contour", "draw_views", "ear_box", "fitted_ear_contour",
    "ict_ear_renderer", "load_contour_file", "main", "render_key", "score_detection",
    "template_ear_contour", "train", "usable", "visible_points",
]
