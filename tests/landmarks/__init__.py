"""Tests of facecap_core.landmarks, one file per module."""
