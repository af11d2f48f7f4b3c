"""Tests of facecap_core.fitting: the fit of a template (NICP through the stage), its files, its checks."""
