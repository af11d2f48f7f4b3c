"""Deployments of facecap's flows (served on demand and on a nightly schedule). Installed as
``facecap.deploy``."""
