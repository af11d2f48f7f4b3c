"""Tests of facecap_core.evaluation."""
