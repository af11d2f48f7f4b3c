"""Camera poses of the keyframes: geometric initialisation, photometric bundle adjustment,
and their outputs. ``main`` is the pose stage (see ``stage.py``); ``cameras_json`` is the
format of its ``cameras.json``."""

__all__ = ["main"]


def __getattr__(name: str):
    if name == "main":
        # Loaded on first use (COLMAP, PBA): a reader of cameras.json needs only cameras_json.
        from facecap_core.pose.stage import main

        return main
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
