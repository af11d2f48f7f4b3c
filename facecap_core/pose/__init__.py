"""Camera poses of the keyframes: geometric initialisation, photometric bundle adjustment,
and their outputs. ``main`` is the pose stage (see ``stage.py``)."""

from facecap_core.pose.stage import main

__all__ = ["main"]
