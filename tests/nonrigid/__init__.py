"""Tests of facecap_core.nonrigid."""
