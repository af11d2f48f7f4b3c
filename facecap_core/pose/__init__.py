"""Camera poses of the keyframes: geometric initialisation and its outputs."""
