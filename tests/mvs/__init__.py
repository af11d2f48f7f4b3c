"""Tests of facecap_core.mvs, one file per module."""
