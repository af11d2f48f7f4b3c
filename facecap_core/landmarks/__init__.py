"""Face landmarks in 3D: the landmark stage (:mod:`.stage`) detects the 68 points of every
keyframe (:mod:`facecap_core.face`: MediaPipe's face mesh, Apache-2.0, its models inside the
wheel), triangulates them over the keyframes (:mod:`.triangulate`), moves them from the 2D
convention to 3D landmarks (:mod:`.convention`), and measures the irises (:mod:`.iris`) and the
ears (:mod:`.ears`, the project's own dlib models)."""
