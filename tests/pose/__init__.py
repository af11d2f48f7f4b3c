"""Tests of facecap_core.pose, one file per module."""
